// The only file of the library that includes Embree (STYLE.md point 2; the benchmarks'
// baselines in bench_trace.cpp call it directly).
#include "engine/embree_scene.h"

#include "engine/float_mode.h"

#include <embree3/rtcore.h>
#if defined(__SSE2__) && !defined(BEAMPACK_NO_SSE)
#include <emmintrin.h>
#endif

#include <algorithm>
#include <atomic>
#include <bit>
#include <chrono>
#include <cmath>
#include <cstdint>
#include <exception>
#include <future>
#include <mutex>
#include <string>
#include <system_error>
#include <thread>
#include <utility>

#include "geometry/compensated_sum.h"
#include "geometry/error.h"
#include "geometry/morton.h"
#include "geometry/ray_sphere.h"

namespace beampack {
namespace {

constexpr double kInf = std::numeric_limits<double>::infinity();
// Relative pad on float bounds and culling distances: float rounding of origins (~6e-8 of the
// coordinates) and of Embree's slab tests stays far below it, so no double hit is culled.
constexpr double kFloatPad = 1e-6;

// Spheres packed as {x, y, z, r} and stored in Morton order: a BVH leaf's spheres then share
// cache lines. Measured: with separate centre/radius arrays in packing order, the callback's
// loads of the sphere were ~55% of its time (cache misses, two per sphere); see
// docs/bench/optics.md. The Particles arrays stay the source of truth; this is a cache of them.
struct alignas(32) SphereRecord {
  Vec3 centre;
  double radius;  // negated once the particle is removed: the callback needs no other load
};
// Also r = 0 or NaN.
bool is_removed(const SphereRecord& s) {
  return !(s.radius > 0.0);
}

// One user geometry: a run of spheres in Morton order (the whole packing, or one brick). Its
// pointers start at the geometry's first sphere; a primitive is a cluster of `per_prim`
// consecutive spheres (1 by default; the last cluster may be shorter).
struct SphereSet {
  Vec3 frame;  // Embree's float coordinates are taken relative to it (the scene's centre)
  const SphereRecord* spheres;
  const std::uint32_t* particle;  // particle id of each sphere
  std::uint32_t first;            // Morton rank of sphere 0
  std::uint32_t count;            // spheres in this geometry
  std::uint32_t per_prim;
  std::uint32_t begin(unsigned prim) const { return prim * per_prim; }
  std::uint32_t end(unsigned prim) const { return std::min(count, (prim + 1) * per_prim); }
};

// RTCIntersectContext extended with the double side arrays (Embree passes it to the callbacks
// untouched; base must be the first member). Embree's ray id is the ray's slot in the packet
// handed to Embree, not the lane a callback sees it in: where 16-wide packets are not native
// (AVX2 and below), Embree splits them into narrower packets or single rays, so a callback's
// lane i may be any slot. Everything per ray is therefore looked up by slot.
struct QueryContext {
  RTCIntersectContext base;
  RayQuery query;
  double slack;                 // absolute pad of the float culling distance
  float prefilter_pad;          // 10 slack: the packet prefilter's margin
  std::uint32_t ray_id[16];     // per slot: the ray's id in the query
  std::uint32_t skip_rank[16];  // per slot: Morton rank of the sphere just left (no id lookup)
  double shift[16];             // per slot: Embree's t = the double t - shift (clip_to_scene)
};

float round_down(double x) {
  float f = static_cast<float>(x);
  return f > x ? std::nextafter(f, -std::numeric_limits<float>::infinity()) : f;
}
float round_up(double x) {
  const float f = static_cast<float>(x);
  return f < x ? std::nextafter(f, std::numeric_limits<float>::infinity()) : f;
}
// The float culling distance of a hit at x >= 0: called on every accepted hit, so no libm call
// and no branch (whether the nearest float lies above or below x is a coin toss). For x >= 0 the
// next float up is the next bit pattern (up to +infinity).
float round_up_distance(double x) {
  const float f = static_cast<float>(x);
  return std::bit_cast<float>(std::bit_cast<std::uint32_t>(f) + static_cast<std::uint32_t>(f < x));
}
// Embree's float tfar for a double hit distance t: padded upward, so Embree never culls a sphere
// the double test would find nearer.
float culling_distance(double t, double slack) {
  return round_up_distance(t * (1.0 + kFloatPad) + slack);
}

// Bounds of a cluster's live spheres, rounded outward; empty when all are removed (dropped by
// builds and refits).
void sphere_bounds(const RTCBoundsFunctionArguments* args) {
  const auto* set = static_cast<const SphereSet*>(args->geometryUserPtr);
  Box box;
  for (std::uint32_t k = set->begin(args->primID); k < set->end(args->primID); ++k) {
    const SphereRecord& s = set->spheres[k];
    if (is_removed(s)) continue;
    const Vec3 centre = s.centre - set->frame;
    box.grow(centre, s.radius + kFloatPad * (s.radius + centre.cwiseAbs().maxCoeff()));
  }
  RTCBounds* b = args->bounds_o;
  if (box.empty()) {
    b->lower_x = b->lower_y = b->lower_z = std::numeric_limits<float>::infinity();
    b->upper_x = b->upper_y = b->upper_z = -std::numeric_limits<float>::infinity();
    return;
  }
  b->lower_x = round_down(box.lower.x());
  b->lower_y = round_down(box.lower.y());
  b->lower_z = round_down(box.lower.z());
  b->upper_x = round_up(box.upper.x());
  b->upper_y = round_up(box.upper.y());
  b->upper_z = round_up(box.upper.z());
}

// Ties in t go to the lower particle id so the answer does not depend on traversal order.
bool improves(const RayQuery& q, unsigned id, double t, std::uint32_t p) {
  return t < q.t_hit[id] || (t == q.t_hit[id] && p < q.particle[id]);
}

// Packets: a float test over the whole packet first keeps only the lanes whose ray passes within
// r + pad of the centre, pad far above float round-off; most lanes of a coherent packet miss any
// given sphere and never reach the double test. Four lanes per SSE step; the kept lanes come back
// as bits, so the double test visits only them (no branch per lane).
#if defined(__SSE2__) && !defined(BEAMPACK_NO_SSE)
template <unsigned W>
std::uint32_t packet_candidates(const int* valid, RTCRayN* rays, const SphereRecord& sphere,
                                const Vec3& frame, float pad) {
  const Vec3 c = sphere.centre - frame;
  const __m128 cx = _mm_set1_ps(static_cast<float>(c.x()));
  const __m128 cy = _mm_set1_ps(static_cast<float>(c.y()));
  const __m128 cz = _mm_set1_ps(static_cast<float>(c.z()));
  const float r = static_cast<float>(sphere.radius) + pad;
  const __m128 reach2 = _mm_set1_ps(r * r), minus_reach = _mm_set1_ps(-r);
  std::uint32_t bits = 0;
  for (unsigned g = 0; g < W; g += 4) {
    const __m128 dx = _mm_loadu_ps(&RTCRayN_dir_x(rays, W, g));
    const __m128 dy = _mm_loadu_ps(&RTCRayN_dir_y(rays, W, g));
    const __m128 dz = _mm_loadu_ps(&RTCRayN_dir_z(rays, W, g));
    const __m128 fx = _mm_sub_ps(_mm_loadu_ps(&RTCRayN_org_x(rays, W, g)), cx);
    const __m128 fy = _mm_sub_ps(_mm_loadu_ps(&RTCRayN_org_y(rays, W, g)), cy);
    const __m128 fz = _mm_sub_ps(_mm_loadu_ps(&RTCRayN_org_z(rays, W, g)), cz);
    const __m128 b = _mm_sub_ps(
        _mm_setzero_ps(),
        _mm_add_ps(_mm_add_ps(_mm_mul_ps(fx, dx), _mm_mul_ps(fy, dy)), _mm_mul_ps(fz, dz)));
    const __m128 px = _mm_add_ps(fx, _mm_mul_ps(b, dx));
    const __m128 py = _mm_add_ps(fy, _mm_mul_ps(b, dy));
    const __m128 pz = _mm_add_ps(fz, _mm_mul_ps(b, dz));
    const __m128 p2 =
        _mm_add_ps(_mm_add_ps(_mm_mul_ps(px, px), _mm_mul_ps(py, py)), _mm_mul_ps(pz, pz));
    const __m128 on = _mm_castsi128_ps(_mm_cmpeq_epi32(
        _mm_loadu_si128(reinterpret_cast<const __m128i*>(valid + g)), _mm_set1_epi32(-1)));
    const __m128 keep =
        _mm_and_ps(on, _mm_and_ps(_mm_cmple_ps(p2, reach2), _mm_cmpgt_ps(b, minus_reach)));
    bits |= static_cast<std::uint32_t>(_mm_movemask_ps(keep)) << g;
  }
  return bits;
}
#else
// The same test one lane at a time, in the same float operations (machines without SSE2; also
// built on x86 with -DBEAMPACK_NO_SSE to test it).
template <unsigned W>
std::uint32_t packet_candidates(const int* valid, RTCRayN* rays, const SphereRecord& sphere,
                                const Vec3& frame, float pad) {
  const Vec3 c = sphere.centre - frame;
  const float cx = static_cast<float>(c.x()), cy = static_cast<float>(c.y()),
              cz = static_cast<float>(c.z());
  const float r = static_cast<float>(sphere.radius) + pad;
  std::uint32_t bits = 0;
  for (unsigned i = 0; i < W; ++i) {
    const float dx = RTCRayN_dir_x(rays, W, i), dy = RTCRayN_dir_y(rays, W, i),
                dz = RTCRayN_dir_z(rays, W, i);
    const float fx = RTCRayN_org_x(rays, W, i) - cx, fy = RTCRayN_org_y(rays, W, i) - cy,
                fz = RTCRayN_org_z(rays, W, i) - cz;
    const float b = -(fx * dx + fy * dy + fz * dz);
    const float px = fx + b * dx, py = fy + b * dy, pz = fz + b * dz;
    const bool keep = valid[i] == -1 && px * px + py * py + pz * pz <= r * r && b > -r;
    bits |= static_cast<std::uint32_t>(keep) << i;
  }
  return bits;
}
#endif

std::uint32_t candidates(const RTCIntersectFunctionNArguments* args, const SphereRecord& sphere,
                         const Vec3& frame, float pad) {
  RTCRayN* rays = RTCRayHitN_RayN(args->rayhit, args->N);
  if (args->N == 16) return packet_candidates<16>(args->valid, rays, sphere, frame, pad);
  if (args->N == 8) return packet_candidates<8>(args->valid, rays, sphere, frame, pad);
  std::uint32_t bits = 0;
  for (unsigned i = 0; i < args->N; ++i)
    bits |= static_cast<std::uint32_t>(args->valid[i] == -1) << i;
  return bits;
}

// The double test on the candidate lanes: first every lane's entry distance (independent
// lanes, so their square roots and divisions overlap), then the nearer ones are taken. Only the
// double side arrays carry the answer; Embree's own hit record is left alone, and its float tfar
// is lowered (padded upward: Embree may still offer spheres the double test finds nearer, it must
// never cull them).
void intersect_sphere(const RTCIntersectFunctionNArguments* args, const SphereSet& set,
                      std::uint32_t k) {
  const SphereRecord& sphere = set.spheres[k];
  if (is_removed(sphere)) return;
  const auto& ctx = *reinterpret_cast<const QueryContext*>(args->context);
  const RayQuery& q = ctx.query;
  const std::uint32_t rank = set.first + k;
  RTCRayN* rays = RTCRayHitN_RayN(args->rayhit, args->N);
  unsigned lanes[16], slots[16], ids[16], m = 0;
  double t[16];
  for (std::uint32_t bits = candidates(args, sphere, set.frame, ctx.prefilter_pad); bits != 0;
       bits &= bits - 1) {
    const unsigned i = static_cast<unsigned>(__builtin_ctz(bits));
    const unsigned slot = RTCRayN_id(rays, args->N, i);
    lanes[m] = i, slots[m] = slot, ids[m] = ctx.ray_id[slot];
    m += ctx.skip_rank[slot] != rank;  // never the sphere the ray has just left
  }
  for (unsigned j = 0; j < m; ++j)
    t[j] = ray_sphere_entry(q.origin[ids[j]], q.direction[ids[j]], sphere.centre, sphere.radius);
  const std::uint32_t p = set.particle[k];
  for (unsigned j = 0; j < m; ++j) {
    const unsigned id = ids[j];
    if (!(t[j] < kNoHit) || !improves(q, id, t[j], p)) continue;
    q.t_hit[id] = t[j];
    q.particle[id] = p;
    // The normal now, while the sphere is in cache; the tracer needs it in double.
    if (q.normal)
      q.normal[id] =
          entry_normal(q.origin[id], q.direction[id], t[j], sphere.centre, sphere.radius);
    const double from_clip = std::max(t[j] - ctx.shift[slots[j]], 0.0);  // >= 0 but for round-off
    RTCRayN_tfar(rays, args->N, lanes[j]) = culling_distance(from_clip, ctx.slack);
  }
}

void sphere_intersect(const RTCIntersectFunctionNArguments* args) {
  const auto* set = static_cast<const SphereSet*>(args->geometryUserPtr);
  for (std::uint32_t k = set->begin(args->primID); k < set->end(args->primID); ++k)
    intersect_sphere(args, *set, k);
}

// Shadow query: any outside hit nearer than query.t_hit[id].
void sphere_occluded(const RTCOccludedFunctionNArguments* args) {
  const auto* set = static_cast<const SphereSet*>(args->geometryUserPtr);
  const auto& ctx = *reinterpret_cast<const QueryContext*>(args->context);
  const RayQuery& q = ctx.query;
  const unsigned n = args->N;
  for (std::uint32_t k = set->begin(args->primID); k < set->end(args->primID); ++k) {
    const SphereRecord& sphere = set->spheres[k];
    if (is_removed(sphere)) continue;
    for (unsigned i = 0; i < n; ++i) {
      if (args->valid[i] != -1) continue;
      const unsigned slot = RTCRayN_id(args->ray, n, i);
      if (ctx.skip_rank[slot] == set->first + k) continue;
      const unsigned id = ctx.ray_id[slot];
      const double t =
          ray_sphere_entry(q.origin[id], q.direction[id], sphere.centre, sphere.radius);
      if (t < q.t_hit[id]) {
        q.particle[id] = set->particle[k];
        RTCRayN_tfar(args->ray, n, i) = -std::numeric_limits<float>::infinity();
      }
    }
  }
}

const char* error_name(RTCError code) {
  switch (code) {
    case RTC_ERROR_NONE:
      return "RTC_ERROR_NONE";
    case RTC_ERROR_UNKNOWN:
      return "RTC_ERROR_UNKNOWN";
    case RTC_ERROR_INVALID_ARGUMENT:
      return "RTC_ERROR_INVALID_ARGUMENT";
    case RTC_ERROR_INVALID_OPERATION:
      return "RTC_ERROR_INVALID_OPERATION";
    case RTC_ERROR_OUT_OF_MEMORY:
      return "RTC_ERROR_OUT_OF_MEMORY";
    case RTC_ERROR_UNSUPPORTED_CPU:
      return "RTC_ERROR_UNSUPPORTED_CPU";
    case RTC_ERROR_CANCELLED:
      return "RTC_ERROR_CANCELLED";
  }
  return "an RTCError unknown to this build";
}

// What Embree's device reports through its callbacks, on whatever thread raised it (a build's
// workers, a tracing thread): its errors, kept here for the calling thread to throw (no
// exception may unwind through Embree's C interface), and the bytes its allocations hold.
struct DeviceReport {
  std::mutex mutex;            // guards the three below; taken only once something failed
  std::string errors;          // reported since the last check, each ending in "; "
  std::size_t new_errors = 0;  // how many (a message may be lost for want of memory)
  std::string broken;          // the failed build that left the scene without a structure
  // Errors pending, or the scene broken. Every query reads it after Embree returns: a relaxed
  // load of a line no one writes while all goes well, so queries pay no lock.
  std::atomic<bool> failed{false};
  std::atomic<RTCError> last_code{RTC_ERROR_NONE};
  std::atomic<std::int64_t> bytes_held{0};
  std::atomic<std::int64_t> byte_limit{std::numeric_limits<std::int64_t>::max()};
};

// Embree's error callback: runs inside Embree, so it must not throw (noexcept: a failure to lock
// ends the program rather than unwind through C).
void record_error(void* user, RTCError code, const char* message) noexcept {
  auto& report = *static_cast<DeviceReport*>(user);
  report.last_code.store(code, std::memory_order_relaxed);
  std::lock_guard lock(report.mutex);
  ++report.new_errors;
  try {
    report.errors += std::string("Embree error ") + error_name(code) + " (" +
                     std::to_string(static_cast<int>(code)) +
                     "): " + (message ? message : "(no message)") + "; ";
  } catch (...) {  // no room for the message: check() names the code alone
  }
  report.failed.store(true, std::memory_order_release);
}

// Embree's allocations are counted (bytes < 0: a free); one asked for (post = false) beyond the
// byte limit is refused, and Embree fails the build or update with RTC_ERROR_OUT_OF_MEMORY.
bool monitor_memory(void* user, ssize_t bytes, bool post) noexcept {
  auto& report = *static_cast<DeviceReport*>(user);
  const std::int64_t held = report.bytes_held.fetch_add(bytes, std::memory_order_relaxed) + bytes;
  if (post || bytes <= 0 || held <= report.byte_limit.load(std::memory_order_relaxed)) return true;
  report.bytes_held.fetch_sub(bytes, std::memory_order_relaxed);  // refused: never allocated
  return false;
}

// One structure Embree traverses: a device (its errors and allocations reported apart), a scene,
// and the sphere records its geometries point into. SceneUpdate::background builds the next one
// on another thread, over its own copy of the records, while this one serves the queries.
struct Structure {
  DeviceReport report;
  RTCDevice device = nullptr;
  RTCScene scene = nullptr;
  std::vector<SphereRecord> spheres;  // Morton order; a removed sphere's radius is negated
  std::vector<SphereSet> sets;        // one per geometry, pointing into `spheres`
  std::vector<RTCGeometry> geometries;

  Structure(std::vector<SphereRecord> records, std::int64_t byte_limit)
      : spheres(std::move(records)) {
    report.byte_limit.store(byte_limit, std::memory_order_relaxed);
  }
  Structure(const Structure&) = delete;
  Structure& operator=(const Structure&) = delete;
  ~Structure() {
    for (RTCGeometry g : geometries) rtcReleaseGeometry(g);
    if (scene) rtcReleaseScene(scene);
    if (device) rtcReleaseDevice(device);
  }

  // Throws the errors Embree reported since the last check, naming what was being done. Called
  // after every build and update (build = true) and after every query (check_query). A failed
  // build leaves Embree without a structure, and its queries then miss every sphere without an
  // error (Embree 3.13): the scene stays failed, every later query throws, until a build succeeds.
  void check(const char* what, bool build) {
    if (!report.failed.load(std::memory_order_acquire)) return;
    std::string message = std::string(what) + ": ";
    {
      std::lock_guard lock(report.mutex);
      const bool reported = report.new_errors > 0;
      if (reported && report.errors.empty())  // no room for the messages
        report.errors = std::string("Embree error ") +
                        error_name(report.last_code.load(std::memory_order_relaxed)) + "; ";
      if (!report.errors.empty()) report.errors.resize(report.errors.size() - 2);  // the last "; "
      message += report.errors;
      report.errors.clear();
      report.new_errors = 0;
      const std::int64_t limit = report.byte_limit.load(std::memory_order_relaxed);
      if (reported && limit < std::numeric_limits<std::int64_t>::max())
        message += " (Embree's allocations limited to " + std::to_string(limit) +
                   " bytes by limit_memory)";
      if (build) {
        report.broken = reported ? message : std::string();
      } else if (!report.broken.empty()) {
        message +=
            std::string(reported ? "; " : "") + "no structure to trace since " + report.broken;
      } else if (!reported) {  // a concurrent query took the errors: this one saw them too
        message += std::string("Embree error ") +
                   error_name(report.last_code.load(std::memory_order_relaxed));
      }
      report.failed.store(!report.broken.empty(), std::memory_order_relaxed);
      if (build && !reported) return;
    }
    throw RunError(message);
  }
  void check_query(const char* what) {
    if (report.failed.load(std::memory_order_relaxed)) [[unlikely]]
      check(what, false);
  }
};

// Bit 0 of a build's progress: Embree asks between its steps and stops when told (a background
// build the scene no longer wants: RTC_ERROR_CANCELLED, and the structure is dropped).
bool keep_building(void* cancel, double) noexcept {
  return !static_cast<const std::atomic<bool>*>(cancel)->load(std::memory_order_relaxed);
}

}  // namespace

struct EmbreeScene::Impl {
  // Fixed at construction, shared by every structure built.
  SceneUpdate update = SceneUpdate::deferred;
  std::string device_config;
  std::vector<std::uint32_t> particle;  // particle id of each sphere
  std::vector<std::uint32_t> rank;      // sphere (Morton rank) of each particle
  std::size_t brick_size = 0;           // spheres per geometry (bricks mode: contiguous runs)
  std::size_t per_prim = 1;             // spheres per primitive
  // Embree sees coordinates relative to `frame`, the centre of the live spheres' box, and rays
  // clipped to `reach`, that box padded (clip_to_scene): float spacing then scales with the
  // packing's size, not with its distance from the origin or the rays' from it.
  Vec3 frame = Vec3::Zero();
  Box reach;
  double slack = 0.0;
  std::atomic<std::int64_t> byte_limit{std::numeric_limits<std::int64_t>::max()};

  std::unique_ptr<Structure> live;  // what the queries traverse

  // SceneUpdate::background: at most one build in flight. The builder thread owns `next`,
  // `next_error` and its copy of the records until it sets `built`; the calling thread masks the
  // particles removed meanwhile in `live` and lists them for `next`.
  std::thread builder;
  std::atomic<bool> built{false};
  std::atomic<bool> cancel{false};
  std::unique_ptr<Structure> next;
  std::exception_ptr next_error;
  std::vector<std::uint32_t> removed_while_building;
  std::vector<SphereRecord> records;  // the builder's copy, until it hands it to build()
  // The records of the structure before the live one, kept for the next build's copy (pages in
  // memory already): the copy is the removal's cost that starts a build. The first spare is
  // allocated and touched on another thread from the first removal on (prepare_spare), not at
  // construction: a scene that never loses a particle never holds one.
  std::vector<SphereRecord> spare;
  std::future<std::vector<SphereRecord>> touched_spare;

  bool spare_ready() const {
    return !spare.empty() || !touched_spare.valid() ||
           touched_spare.wait_for(std::chrono::seconds(0)) == std::future_status::ready;
  }
  void prepare_spare() {
    if (!spare.empty() || touched_spare.valid() || building()) return;
    try {
      touched_spare = std::async(std::launch::async, [n = live->spheres.size()] {
        return std::vector<SphereRecord>(n, SphereRecord{Vec3::Zero(), 0.0});  // every page
      });
    } catch (const std::system_error&) {  // no thread to be had: the copy will fault its pages
    }
  }

  ~Impl() {
    if (!builder.joinable()) return;
    cancel.store(true, std::memory_order_relaxed);  // the build is not wanted: stop it early
    builder.join();
  }

  bool building() const { return builder.joinable(); }

  // Embree's frame and float margins from the live spheres' box. A sample far from the origin (a
  // DEM frame in metres, spheres of microns) has float spacing of many radii in world
  // coordinates: bounds padded for it overlapped by hundreds of radii, and tracing was 26 times
  // slower. Relative to the box's centre, and with rays clipped to the box (clip_to_scene), float
  // error scales with the box; the slack covers it in culling distances and the packet
  // prefilter, and the double round-off of world coordinates in hit distances besides. Ray
  // starts are computed without that round-off (clipped_start): the bounds' pads do not cover it.
  void set_frame(const Box& box) {
    if (box.empty()) return;
    frame = 0.5 * (box.lower + box.upper);
    const Vec3 half = 0.5 * (box.upper - box.lower);
    const double world = box.lower.cwiseAbs().cwiseMax(box.upper.cwiseAbs()).maxCoeff();
    slack = kFloatPad * (2.0 * half.norm() + half.maxCoeff()) + 1e-12 * world;
    reach = box;
    reach.lower.array() -= 4.0 * slack;
    reach.upper.array() += 4.0 * slack;
  }

  // A device, a scene and its geometries over `records`, committed. Embree's errors are left in
  // the structure's report for the caller to check (Structure::check); a device Embree refuses
  // is a RunError at once. With `stop`, the build stops when it turns true.
  std::unique_ptr<Structure> build(std::vector<SphereRecord> records,
                                   const std::atomic<bool>* stop) const;

  // Ray `id` clipped to the scene, as Embree's single ray with its context: false when no sphere
  // can improve on the ray's nearest hit (nothing to trace).
  bool single_ray(const RayQuery& query, std::uint32_t id, QueryContext& ctx, RTCRay& ray) const;

  std::uint32_t rank_of(std::uint32_t p) const { return p < rank.size() ? rank[p] : kNoParticle; }

  // Background mode: a build of the live records as they are now, on another thread. False when
  // it could not start (noted as a failure).
  bool start_rebuild();
  // Background mode: puts a finished build in the place of the live structure (with `wait`, waits
  // for one in flight), true when it did. The particles removed while it was built are masked in
  // it first. A failed build is noted (failures, last_failure), not thrown: the live structure,
  // removals masked in it, stays and is correct.
  bool adopt_rebuild(bool wait);
  std::size_t failures = 0;
  std::size_t failures_seen = 0;  // by finish_rebuild, which throws the new ones
  std::string last_failure;
  void note_failure(std::string what) {
    ++failures;
    last_failure = std::move(what);
  }
};

namespace {

// Particle ids sorted along a Morton curve over the particles' box: nearby spheres end up
// nearby in memory, and any contiguous run of them is a compact spatial brick.
std::vector<std::uint32_t> morton_order(const Particles& particles) {
  const std::size_t n = particles.size();
  Box box;
  for (std::size_t i = 0; i < n; ++i) box.grow(particles.centre[i], 0.0);
  const Vec3 extent = box.empty() ? Vec3(Vec3::Ones())
                                  : Vec3((box.upper - box.lower).cwiseMax(Vec3::Constant(1e-300)));
  std::vector<std::pair<std::uint64_t, std::uint32_t>> keyed(n);
  for (std::size_t i = 0; i < n; ++i) {
    std::uint64_t q[3];
    for (int a = 0; a < 3; ++a) {
      const double u = (particles.centre[i][a] - box.lower[a]) / extent[a];
      q[a] = static_cast<std::uint64_t>(std::clamp(u, 0.0, 1.0) * kMortonMax);
    }
    keyed[i] = {morton_code(q[0], q[1], q[2]), static_cast<std::uint32_t>(i)};
  }
  std::sort(keyed.begin(), keyed.end());
  std::vector<std::uint32_t> order(n);
  for (std::size_t k = 0; k < n; ++k) order[k] = keyed[k].second;
  return order;
}

}  // namespace

std::unique_ptr<Structure> EmbreeScene::Impl::build(std::vector<SphereRecord> records,
                                                    const std::atomic<bool>* stop) const {
  auto st =
      std::make_unique<Structure>(std::move(records), byte_limit.load(std::memory_order_relaxed));
  st->device = rtcNewDevice(device_config.empty() ? nullptr : device_config.c_str());
  if (!st->device)
    throw RunError("Embree: rtcNewDevice(\"" + device_config + "\") failed (" +
                   error_name(rtcGetDeviceError(nullptr)) + ")");
  rtcSetDeviceErrorFunction(st->device, record_error, &st->report);
  rtcSetDeviceMemoryMonitorFunction(st->device, monitor_memory, &st->report);
  st->scene = rtcNewScene(st->device);
  // Per-geometry build quality (refit, bricks) is honoured only under a LOW-quality scene,
  // which builds two levels: one BVH per geometry and a top level over them.
  const bool two_level = update == SceneUpdate::refit || update == SceneUpdate::bricks;
  rtcSetSceneBuildQuality(st->scene, two_level ? RTC_BUILD_QUALITY_LOW : RTC_BUILD_QUALITY_MEDIUM);
  if (update == SceneUpdate::bricks) rtcSetSceneFlags(st->scene, RTC_SCENE_FLAG_DYNAMIC);
  if (stop)
    rtcSetSceneProgressMonitorFunction(st->scene, keep_building,
                                       const_cast<std::atomic<bool>*>(stop));
  const std::size_t n = st->spheres.size();
  const std::size_t geometries = std::max<std::size_t>(1, (n + brick_size - 1) / brick_size);
  st->sets.reserve(geometries);  // never reallocated: the geometries point at their sets
  for (std::size_t b = 0; b < geometries; ++b) {
    const std::size_t first = b * brick_size;
    const std::size_t count = std::min(n, first + brick_size) - std::min(n, first);
    st->sets.push_back({frame, st->spheres.data() + first, particle.data() + first,
                        static_cast<std::uint32_t>(first), static_cast<std::uint32_t>(count),
                        static_cast<std::uint32_t>(per_prim)});
    RTCGeometry g = rtcNewGeometry(st->device, RTC_GEOMETRY_TYPE_USER);
    rtcSetGeometryUserPrimitiveCount(g, static_cast<unsigned>((count + per_prim - 1) / per_prim));
    rtcSetGeometryUserData(g, &st->sets.back());
    rtcSetGeometryBoundsFunction(g, sphere_bounds, nullptr);
    rtcSetGeometryIntersectFunction(g, sphere_intersect);
    rtcSetGeometryOccludedFunction(g, sphere_occluded);
    rtcSetGeometryBuildQuality(
        g, update == SceneUpdate::refit ? RTC_BUILD_QUALITY_REFIT : RTC_BUILD_QUALITY_LOW);
    rtcCommitGeometry(g);
    rtcAttachGeometry(st->scene, g);
    st->geometries.push_back(g);
  }
  const KeepFloatMode keep;  // Embree's build may set FTZ/DAZ on this thread
  rtcCommitScene(st->scene);
  return st;
}

bool EmbreeScene::Impl::start_rebuild() {
  try {
    // The builder's own copy (no race on the masks), written into pages already touched: into
    // fresh ones, the copy took 82 ms at 1e6 on the 2-core VM (page faults), into these ~3 ms.
    if (spare.empty() && touched_spare.valid()) spare = touched_spare.get();
    spare.assign(live->spheres.begin(), live->spheres.end());
    records = std::exchange(spare, {});
    built.store(false, std::memory_order_relaxed);
    builder = std::thread([this] {
      try {
        next = build(std::move(records), &cancel);
      } catch (...) {
        next_error = std::current_exception();
      }
      built.store(true, std::memory_order_release);
    });
    return true;
  } catch (const std::exception& e) {  // no memory for the copy, or no thread to be had
    if (spare.empty()) spare = std::move(records);
    note_failure(std::string("starting the background rebuild of the particle scene: ") + e.what());
    return false;
  }
}

bool EmbreeScene::Impl::adopt_rebuild(bool wait) {
  if (!building() || (!wait && !built.load(std::memory_order_acquire))) return false;
  builder.join();
  std::unique_ptr<Structure> fresh = std::move(next);
  const std::vector<std::uint32_t> late = std::exchange(removed_while_building, {});
  const std::string what = "rebuilding the particle scene in the background";
  try {
    if (next_error) std::rethrow_exception(std::exchange(next_error, nullptr));
    fresh->check(what.c_str(), true);
  } catch (const std::exception& e) {
    // A build that threw (no device, no memory) made no structure, and its message no context.
    note_failure(fresh ? e.what() : what + ": " + e.what());
    if (fresh) spare = std::move(fresh->spheres);  // for the next try
    return false;
  }
  for (std::uint32_t p : late)
    fresh->spheres[rank[p]].radius = -std::abs(fresh->spheres[rank[p]].radius);
  std::swap(live, fresh);
  spare = std::move(fresh->spheres);  // no query runs: the old structure goes unused from here
  return true;
}

EmbreeScene::EmbreeScene(const Particles& particles, SceneUpdate update,
                         std::size_t particles_per_brick, double rebuild_fraction,
                         unsigned spheres_per_primitive, const std::string& device_config)
    : rebuild_fraction_(rebuild_fraction), impl_(std::make_unique<Impl>()) {
  Impl& im = *impl_;
  const std::size_t n = particles.size();
  removed_.resize(n);
  im.update = update;
  im.device_config = device_config;
  im.particle = morton_order(particles);
  im.rank.resize(n);
  std::vector<SphereRecord> records(n);
  for (std::size_t k = 0; k < n; ++k) {
    const std::uint32_t p = im.particle[k];
    im.rank[p] = static_cast<std::uint32_t>(k);
    removed_[p] = particles.alive[p] ? 0 : 1;
    records[k] = {particles.centre[p], removed_[p] ? -particles.radius[p] : particles.radius[p]};
  }
  im.per_prim = std::clamp(spheres_per_primitive, 1u, 64u);  // the Tracer refuses others
  // Bricks hold whole clusters.
  im.brick_size = update == SceneUpdate::bricks
                      ? im.per_prim * std::max<std::size_t>(1, particles_per_brick / im.per_prim)
                      : std::max<std::size_t>(1, n);
  im.set_frame(particles.bounds());
  im.live = im.build(std::move(records), nullptr);
  im.live->check("building the particle scene", true);
}

EmbreeScene::~EmbreeScene() = default;

void EmbreeScene::limit_memory(std::size_t bytes) {
  const auto limit = static_cast<std::int64_t>(
      std::min<std::size_t>(bytes, std::numeric_limits<std::int64_t>::max()));
  impl_->byte_limit.store(limit, std::memory_order_relaxed);
  impl_->live->report.byte_limit.store(limit, std::memory_order_relaxed);
}

bool EmbreeScene::rebuilding() const {
  return impl_->building();
}

bool EmbreeScene::rebuild_due() const {
  return masked_in_structure_ > rebuild_fraction_ * static_cast<double>(removed_.size());
}

void EmbreeScene::poll_rebuild() {
  if (impl_->update != SceneUpdate::background) return;
  impl_->adopt_rebuild(false);
  start_rebuild_if_due(false);
}

void EmbreeScene::finish_rebuild() {
  if (impl_->update != SceneUpdate::background) return;
  Impl& im = *impl_;
  im.adopt_rebuild(true);
  start_rebuild_if_due(true);
  im.adopt_rebuild(true);
  if (im.failures == im.failures_seen) return;
  im.failures_seen = im.failures;
  throw RunError(im.last_failure);
}

std::size_t EmbreeScene::failed_rebuilds() const {
  return impl_->failures;
}

const std::string& EmbreeScene::last_failed_rebuild() const {
  return impl_->last_failure;
}

// One build at a time. Put off, to the next removal or poll, while the first spare's pages are
// still being touched (`wait`: waits for them): copied into fresh pages, the records took 82 ms.
// The count restarts with the build, failed or not: after a failure the next try waits for
// another rebuild_fraction of N removed.
void EmbreeScene::start_rebuild_if_due(bool wait) {
  Impl& im = *impl_;
  if (im.building() || !rebuild_due() || (!wait && !im.spare_ready())) return;
  masked_in_structure_ = 0;
  if (im.start_rebuild()) ++rebuilds_;
}

void EmbreeScene::remove(std::span<const std::uint32_t> ids) {
  Impl& im = *impl_;
  check_removal_ids(ids, removed_.size());
  if (im.building())  // no allocation can fail between a mask and its listing
    im.removed_while_building.reserve(im.removed_while_building.size() + ids.size());
  std::size_t masked = 0;
  for (std::uint32_t p : ids) {
    if (removed_[p]) continue;
    removed_[p] = 1;
    SphereRecord& sphere = im.live->spheres[im.rank[p]];
    sphere.radius = -std::abs(sphere.radius);  // masked in the callback from now on
    if (im.building()) im.removed_while_building.push_back(p);
    ++masked;
  }
  masked_in_structure_ += masked;
  if (im.update == SceneUpdate::background) {
    // Counted from the build's start, so an adopted build holds exactly these; never throws
    // for a failed build (poll_rebuild).
    if (masked > 0) im.prepare_spare();
    poll_rebuild();
    return;
  }
  if (ids.empty() || im.update == SceneUpdate::mask_only) return;
  if (im.update == SceneUpdate::deferred) {
    // Masked spheres cost traversal time, not correctness: rebuild only once they are many.
    if (!rebuild_due()) return;
    masked_in_structure_ = 0;
  }
  ++rebuilds_;
  Structure& st = *im.live;
  if (im.update == SceneUpdate::bricks) {
    std::vector<std::size_t> touched;
    touched.reserve(ids.size());
    for (std::uint32_t p : ids) touched.push_back(im.rank[p] / im.brick_size);
    std::sort(touched.begin(), touched.end());
    touched.erase(std::unique(touched.begin(), touched.end()), touched.end());
    for (std::size_t b : touched) rtcCommitGeometry(st.geometries[b]);
  } else {
    rtcCommitGeometry(st.geometries.front());
  }
  {
    const KeepFloatMode keep;  // Embree's build may set FTZ/DAZ on this thread
    rtcCommitScene(st.scene);
  }
  st.check("updating the particle scene", true);
}

namespace {

QueryContext make_context(const RayQuery& query, double slack, bool coherent) {
  QueryContext ctx;
  std::fill(std::begin(ctx.skip_rank), std::end(ctx.skip_rank), kNoParticle);
  rtcInitIntersectContext(&ctx.base);
  ctx.base.flags =
      coherent ? RTC_INTERSECT_CONTEXT_FLAG_COHERENT : RTC_INTERSECT_CONTEXT_FLAG_INCOHERENT;
  ctx.query = query;
  ctx.slack = slack;
  ctx.prefilter_pad = static_cast<float>(10.0 * slack);
  return ctx;
}

// Where a ray enters `reach`, the padded box of the live spheres: the distance t0 >= 0 from which
// Embree traverses it, or -1 when it misses the box or meets it only beyond t_hit, its nearest
// hit so far (no sphere can then improve on it). A primary ray starting far from the packing is
// thus handed to Embree at the packing, not across the float spacing of its distance.
double clip_to_scene(const Box& reach, const Vec3& o, const Vec3& d, double t_hit) {
  if (reach.empty()) return -1.0;
  double t0 = 0.0, t1 = t_hit;
  for (int a = 0; a < 3; ++a) {
    if (d[a] == 0.0) {
      if (o[a] < reach.lower[a] || o[a] > reach.upper[a]) return -1.0;
      continue;
    }
    const double ta = (reach.lower[a] - o[a]) / d[a], tb = (reach.upper[a] - o[a]) / d[a];
    t0 = std::max(t0, std::min(ta, tb));
    t1 = std::min(t1, std::max(ta, tb));
  }
  // Backed off by far more than the round-off of t0 (a few ulps of a ray's distance from the box).
  return t0 <= t1 ? t0 * (1.0 - 1e-12) : -1.0;
}

// o + t0 d - frame, rounded once at its own size. o and frame are world coordinates: summed in
// them, the start would carry their round-off (5e-11 m at 5e5 m), which moves a ray grazing a
// small sphere's bound sideways by more than the pad on the bound, whatever the ray's slope (it
// missed 3% of grazing hits on spheres of 1e-9 m at 5e5 m). The product t0 d keeps its own
// round-off: it is proportional to each component of d, as is the room a grazing ray has
// inside the bound, so it matters only beyond 1e15 radii upstream.
Vec3 clipped_start(const Vec3& o, const Vec3& d, double t0, const Vec3& frame) {
  Vec3 start;
  for (int a = 0; a < 3; ++a) {
    double from_frame_error, sum_error;
    const double from_frame = two_sum(o[a], -frame[a], from_frame_error);
    const double sum = two_sum(from_frame, t0 * d[a], sum_error);
    start[a] = sum + (from_frame_error + sum_error);
  }
  return start;
}

// The float ray Embree traverses for a double ray clipped at t0: its origin o + t0 d relative to
// the frame, rounded; its far end the nearest hit so far, less t0, padded so that no sphere the
// double test accepts is culled.
struct FloatRay {
  float org[3], dir[3], tfar;
};
FloatRay float_ray(const Vec3& o, const Vec3& d, double t_hit, double t0, const Vec3& frame,
                   double slack) {
  const Vec3 start = clipped_start(o, d, t0, frame);
  return {
      {static_cast<float>(start.x()), static_cast<float>(start.y()), static_cast<float>(start.z())},
      {static_cast<float>(d.x()), static_cast<float>(d.y()), static_cast<float>(d.z())},
      t_hit < kInf ? culling_distance(t_hit - t0, slack) : std::numeric_limits<float>::infinity()};
}

RTCRay rtc_ray(const FloatRay& f, std::uint32_t slot) {
  RTCRay ray;
  ray.org_x = f.org[0], ray.org_y = f.org[1], ray.org_z = f.org[2];
  ray.dir_x = f.dir[0], ray.dir_y = f.dir[1], ray.dir_z = f.dir[2];
  ray.tnear = 0.0f;
  ray.tfar = f.tfar;
  ray.time = 0.0f;
  ray.mask = 0xFFFFFFFFu;
  ray.id = slot;
  ray.flags = 0;
  return ray;
}

}  // namespace

bool EmbreeScene::Impl::single_ray(const RayQuery& query, std::uint32_t id, QueryContext& ctx,
                                   RTCRay& ray) const {
  const Vec3& o = query.origin[id];
  const Vec3& d = query.direction[id];
  const double t0 = clip_to_scene(reach, o, d, query.t_hit[id]);
  if (t0 < 0.0) return false;
  ctx = make_context(query, slack, false);
  ctx.ray_id[0] = id;
  ctx.skip_rank[0] = rank_of(query.skip[id]);
  ctx.shift[0] = t0;
  ray = rtc_ray(float_ray(o, d, query.t_hit[id], t0, frame, slack), 0);
  return true;
}

void EmbreeScene::intersect1(const RayQuery& query, std::uint32_t id) const {
  QueryContext ctx;
  RTCRayHit rh;
  if (!impl_->single_ray(query, id, ctx, rh.ray)) return;
  rh.hit.geomID = RTC_INVALID_GEOMETRY_ID;
  rh.hit.instID[0] = RTC_INVALID_GEOMETRY_ID;
  rtcIntersect1(impl_->live->scene, &ctx.base, &rh);
  impl_->live->check_query("tracing a ray (rtcIntersect1)");
}

void EmbreeScene::intersect16(const RayQuery& query, const std::uint32_t* ids, int count,
                              bool coherent) const {
  const Impl& im = *impl_;
  QueryContext ctx = make_context(query, im.slack, coherent);
  alignas(64) RTCRayHit16 rh;
  alignas(64) int valid[16];
  bool any = false;
  // The lanes' own values first, then the fields every lane shares, field by field (stores the
  // compiler can make whole vectors of). A lane that cannot meet a sphere is left out.
  for (int i = 0; i < 16; ++i) {
    const std::uint32_t id = i < count ? ids[i] : ids[0];
    const Vec3& o = query.origin[id];
    const Vec3& d = query.direction[id];
    const double t0 = i < count ? clip_to_scene(im.reach, o, d, query.t_hit[id]) : -1.0;
    valid[i] = t0 >= 0.0 ? -1 : 0;
    any |= t0 >= 0.0;
    ctx.ray_id[i] = id;
    ctx.skip_rank[i] = im.rank_of(query.skip[id]);
    ctx.shift[i] = std::max(t0, 0.0);
    const FloatRay f = float_ray(o, d, query.t_hit[id], ctx.shift[i], im.frame, im.slack);
    rh.ray.org_x[i] = f.org[0], rh.ray.org_y[i] = f.org[1], rh.ray.org_z[i] = f.org[2];
    rh.ray.dir_x[i] = f.dir[0], rh.ray.dir_y[i] = f.dir[1], rh.ray.dir_z[i] = f.dir[2];
    rh.ray.tfar[i] = f.tfar;
    rh.ray.id[i] = static_cast<unsigned>(i);
  }
  if (!any) return;
  std::fill(std::begin(rh.ray.tnear), std::end(rh.ray.tnear), 0.0f);
  std::fill(std::begin(rh.ray.time), std::end(rh.ray.time), 0.0f);
  std::fill(std::begin(rh.ray.mask), std::end(rh.ray.mask), 0xFFFFFFFFu);
  std::fill(std::begin(rh.ray.flags), std::end(rh.ray.flags), 0u);
  std::fill(std::begin(rh.hit.geomID), std::end(rh.hit.geomID), RTC_INVALID_GEOMETRY_ID);
  std::fill(std::begin(rh.hit.instID[0]), std::end(rh.hit.instID[0]), RTC_INVALID_GEOMETRY_ID);
  rtcIntersect16(valid, im.live->scene, &ctx.base, &rh);
  impl_->live->check_query("tracing a packet of rays (rtcIntersect16)");
}

bool EmbreeScene::occluded1(const RayQuery& query, std::uint32_t id) const {
  QueryContext ctx;
  RTCRay ray;
  if (!impl_->single_ray(query, id, ctx, ray)) return false;
  rtcOccluded1(impl_->live->scene, &ctx.base, &ray);
  impl_->live->check_query("a shadow query (rtcOccluded1)");
  return ray.tfar < 0.0f;
}

int embree_native_packet_width() {
  RTCDevice device = rtcNewDevice(nullptr);
  if (!device) return 0;
  const int rays = rtcGetDeviceProperty(device, RTC_DEVICE_PROPERTY_NATIVE_RAY16_SUPPORTED)  ? 16
                   : rtcGetDeviceProperty(device, RTC_DEVICE_PROPERTY_NATIVE_RAY8_SUPPORTED) ? 8
                                                                                             : 4;
  rtcReleaseDevice(device);
  return rays;
}

}  // namespace beampack
