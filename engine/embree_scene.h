#pragma once
// The ray-tracing scene: the particles as Embree user-geometry spheres, behind a small interface.
// This header does not include Embree (pimpl); engine/embree_scene.cpp is the only file of the
// library that does. One benchmark file is the exception: bench_trace.cpp's baselines (Embree's
// built-in spheres) must call Embree directly.
//
// Layout: the user data of each geometry points at a packed copy of the particles' centres and
// radii in Morton order (not straight into the Particles arrays): measured, the callback was
// bound by cache misses on the two separate, randomly ordered arrays. Particles do not move, so
// the copy is made once; removal is the only change and goes through remove().
//
// Precision: Embree rays are float, the physics is double. Every query carries ray ids into
// double side arrays (RayQuery); the intersect callback runs the real test (ray_sphere_entry) in
// double and keeps the best double t per ray. Float bounds are rounded outward and the float
// culling distance is padded, so Embree never culls a sphere the double test would accept. Its
// float coordinates are relative to the packing's centre, and each ray is handed to it from where
// the ray enters the packing's box: float spacing follows the packing's size, not its distance
// from the origin or the beam's from it (26 times slower tracing for a bed 500 m out, before).
#include <cstdint>
#include <memory>
#include <span>
#include <string>

#include "../geometry/particles.h"
#include "ray_query.h"

namespace beampack {

// How the acceleration structure follows removals (benchmarks/bench_trace.cpp compares them;
// docs/bench/optics.md has the numbers). In every mode a removed particle is masked at once in
// the intersect callback, so it is never hit again whatever the structure still holds.
enum class SceneUpdate {
  deferred,    // mask now; rebuild (static SAH) once the spheres masked since the last build
               // exceed rebuild_fraction of all particles (N, not the spheres the structure still
               // holds). Cheapest update and the fastest structure to trace; but the update that
               // rebuilds takes a full build (~0.3-0.4 s at 1e6, BENCHMARKS.md).
  background,  // as deferred, but the rebuild runs on another thread over a copy of the spheres
               // while the current structure (removals masked in it) serves the queries. The
               // removal that starts it pays the copy (2-4 ms at 1e6, into pages touched on
               // another thread since the first removal, or kept from the structure before:
               // fresh ones took 80 ms), then returns. The finished structure
               // takes over at the next remove() or poll_rebuild() (0.2-0.9 ms). Tracing is
               // bit-identical whichever structure answers (the callback's double test and its
               // tie rule decide every hit), so when the swap happens changes no result. Costs:
               // one more copy of the spheres held from the first removal (32 bytes each); during
               // a build two Embree structures (peak ~100 bytes per sphere above deferred's, 308
               // against 211 MB at 1e6; limit_memory caps each); the build shares the cores with
               // whatever runs meanwhile. The tracer's default.
  mask_only,   // keep the structure; removed spheres are culled in the callback only
  rebuild,     // one geometry, static medium-quality build, rebuilt on every update
  refit,       // one geometry, refit with empty bounds for removed spheres
  bricks,      // spatial bricks, one user geometry each, dynamic scene: rebuild touched bricks
};

class EmbreeScene {
 public:
  explicit EmbreeScene(const Particles& particles, SceneUpdate update = SceneUpdate::deferred,
                       std::size_t particles_per_brick = 4096, double rebuild_fraction = 0.1,
                       unsigned spheres_per_primitive = 1, const std::string& device_config = {});
  ~EmbreeScene();
  EmbreeScene(const EmbreeScene&) = delete;
  EmbreeScene& operator=(const EmbreeScene&) = delete;

  // Masks the particles at once (never hit again), then updates the structure per SceneUpdate.
  // Not concurrent with queries (nor are poll_rebuild and finish_rebuild).
  void remove(std::span<const std::uint32_t> ids);
  bool removed(std::uint32_t id) const { return removed_[id] != 0; }
  // Structure updates after construction (background: builds started, adopted or not).
  std::size_t rebuilds() const { return rebuilds_; }
  // Background mode: a build is in flight, or finished and not yet adopted.
  bool rebuilding() const;
  // Background mode (nothing in the others): puts a finished build in place of the structure,
  // with the particles removed since its start masked in it, and starts the build a removal past
  // the threshold put off (while the first spare copy's pages were still being touched). Call it
  // where no query is running (the tracer does, at each launch and advance; remove() does too).
  // A build that failed (Embree's error, no memory for the copy, no thread) throws nothing here:
  // the structure in use stays, correct (removals are masked in it), only slower to trace; the
  // failure is counted and kept (failed_rebuilds, last_failed_rebuild), and the next try comes
  // once another rebuild_fraction of N has been removed.
  void poll_rebuild();
  // The same, waiting: a build in flight or due is finished and in place on return (tests,
  // benchmarks, a caller about to time). Throws RunError, naming the task and Embree's error,
  // for a failure not thrown before.
  void finish_rebuild();
  std::size_t failed_rebuilds() const;
  const std::string& last_failed_rebuild() const;  // empty while none has failed

  // Nearest outside hit of one ray (rtcIntersect1).
  void intersect1(const RayQuery& query, std::uint32_t ray_id) const;
  // Nearest outside hits of up to 16 rays in one packet (rtcIntersect16); coherent: the rays
  // are a tile of a parallel beam (Embree's coherent context flag).
  void intersect16(const RayQuery& query, const std::uint32_t* ray_ids, int count,
                   bool coherent = true) const;
  // True when some particle is hit before query.t_hit[ray_id] (rtcOccluded1).
  bool occluded1(const RayQuery& query, std::uint32_t ray_id) const;
  // Errors: construction and remove() throw RunError when Embree reports one during their build
  // (in background mode, remove() builds nothing itself: see poll_rebuild),
  // and the queries when it reports one during them (on the calling thread, once Embree has
  // returned), naming Embree's error code and what was being done. After a failed build every
  // query throws (Embree has no structure left, and would miss every sphere without an error)
  // until a remove() builds one.

  // From now on Embree's allocations for this scene beyond `bytes` held are refused: the next
  // build (remove()) fails with RTC_ERROR_OUT_OF_MEMORY. No limit by default; tests raise real
  // Embree errors with it. Each structure counts its own (a background build starts at zero, with
  // the limit set when it started).
  void limit_memory(std::size_t bytes);

 private:
  struct Impl;
  bool rebuild_due() const;  // masked since the last build > rebuild_fraction of N
  void start_rebuild_if_due(bool wait);
  double rebuild_fraction_;
  std::size_t masked_in_structure_ = 0;  // removed since the last build (deferred, background)
  std::size_t rebuilds_ = 0;
  std::vector<std::uint8_t> removed_;
  std::unique_ptr<Impl> impl_;
};

// The rays per packet Embree traverses natively on this host (16 with AVX-512, 8 with AVX2, else
// 4), which the packets' speed depends on; 0 when no Embree device could be made.
int embree_native_packet_width();

}  // namespace beampack
