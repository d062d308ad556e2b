// Optics benchmarks, side by side in one run (STYLE.md point 9):
//   trace/workload/<variant>/n<index x10>/<N>/<rays>: the paper's beam (6000 W, d_b = 0.3 D,
//       exponential a = 2) in 10^4 rays, at the paper's resolution (1000 (N/1000)^(2/3) rays),
//       or at 10^6 spheres in the paper's own 1000 rays; on a random-overlap packing
//       (D = 1e-3, L = 0.325), all bounces to the cutoff; variants: this tracer (primary
//       packets, interleaved grid walks), the tracer with Embree single rays or incoherent
//       packets for bounces, single rays only, a plain rtcIntersect1 loop over Embree's built-in
//       spheres, brute force (small N).
//   trace/primary/<variant>/<N>/<rays>: the first segment of every ray only (max_bounces = 1);
//       builtin_sphere_packets: Embree's built-in spheres in the tracer's 16-ray tiles, what
//       Embree's own packets gain on the scene without any callback.
//   trace/paired/<case>[_reused]/<N>/<rays>: this tracer and the built-in loop pulse by pulse,
//       alternately, and the median ratio of their times; _reused: first hits reused from the
//       pulse before. Elsewhere the tracer traces every pulse's primaries (reuse_primaries off).
//   trace/scene_mode, trace/cluster, trace/grid_cell: design choices; trace/grid_batch: the grid
//       walk alone, one ray at a time or interleaved.
//   scene_update/<mode>/<pattern>/<N>: removing 1% of the spheres, random or under the beam.
//   trace/far_frame/<offset>/<N>/<rays>: the workload on a packing moved far from the origin.
// Counters: primary and bounced segments per second (whole-workload time).
#include <benchmark/benchmark.h>
#include <embree3/rtcore.h>  // the baselines call Embree directly on purpose
#include <tbb/blocked_range.h>
#include <tbb/global_control.h>
#include <tbb/parallel_for.h>

#include <algorithm>
#include <atomic>
#include <chrono>
#include <cmath>
#include <cstdlib>
#include <limits>
#include <map>
#include <memory>
#include <numeric>

#include "engine/beam.h"
#include "engine/embree_scene.h"
#include "engine/fresnel.h"
#include "engine/sphere_grid.h"
#include "engine/tracer.h"
#include "geometry/packing.h"
#include "geometry/random.h"
#include "geometry/ray_sphere.h"

namespace beampack {
namespace {

constexpr double kD = 1e-3;
constexpr std::size_t kRays = 10000;

const Particles& packing(std::size_t n) {
  static std::map<std::size_t, std::unique_ptr<Particles>> cache;
  auto& slot = cache[n];
  if (!slot) slot = std::make_unique<Particles>(random_overlap_packing(n, kD, 0.325, 2013));
  return *slot;
}

// The paper's beam (6000 W, 0.3 D, exponential a = 2, +x) split into `rays` rays.
const Beam& paper_beam(std::size_t rays = kRays) {
  static std::map<std::size_t, Beam> cache;
  auto found = cache.find(rays);
  if (found == cache.end()) {
    BeamSpec spec;
    spec.rays = rays;
    found = cache.emplace(rays, make_beam(spec, kD)).first;
  }
  return found->second;
}

// The paper's resolution: 1000 rays on 1000 spheres is ~47 rays per sphere cross-section inside
// the beam; keeping that density as the spheres shrink takes 1000 (N / 1000)^(2/3) rays.
std::size_t paper_resolution_rays(std::size_t spheres) {
  return static_cast<std::size_t>(std::lround(1000.0 * std::cbrt(std::pow(spheres / 1000.0, 2.0))));
}

std::size_t spheres_of(const benchmark::State& state) {
  return static_cast<std::size_t>(state.range(0));
}
std::size_t rays_of(const benchmark::State& state) {
  return static_cast<std::size_t>(state.range(1));
}

void set_counters(benchmark::State& state, double primary, double bounced) {
  state.counters["primary_seg/s"] = benchmark::Counter(primary, benchmark::Counter::kIsRate);
  state.counters["bounced_seg/s"] = benchmark::Counter(bounced, benchmark::Counter::kIsRate);
  state.counters["segments/s"] = benchmark::Counter(primary + bounced, benchmark::Counter::kIsRate);
  state.counters["bounced/ray"] = bounced / std::max(primary, 1.0);
}

// ---- this tracer ----------------------------------------------------------------------------

OpticsSpec tracer_spec(bool packets, double n_hat, int max_bounces,
                       SceneUpdate scene_update = OpticsSpec{}.scene_update,
                       unsigned per_prim = OpticsSpec{}.spheres_per_primitive,
                       BounceSearch bounce = OpticsSpec{}.bounce_search,
                       double cell_factor = OpticsSpec{}.grid_cell_factor) {
  OpticsSpec spec;
  spec.grid_cell_factor = cell_factor;
  spec.bounce_search = bounce;
  spec.scene_update = scene_update;
  spec.spheres_per_primitive = per_prim;
  spec.materials[0].n_solid = n_hat;
  spec.packets = packets;
  spec.max_bounces = max_bounces;
  spec.reuse_primaries = false;  // every pulse traces its primaries: the tracing speed itself
  return spec;
}

// One whole pulse at a time through this tracer: what the simulation does in pulse mode.
struct TracerPulses {
  Tracer tracer;
  const Beam& beam;
  const std::vector<double> energy;  // per ray, as the built-in loop has them
  std::vector<double> deposits;
  TracerPulses(const Particles& p, const OpticsSpec& spec, const Beam& beam)
      : tracer(p, spec), beam(beam), energy(beam.ray_energies(1e-9)), deposits(p.size(), 0.0) {
    tracer.build_scene();  // before the timing: the first launch would build it otherwise
  }
  // Returns the primary and bounced segments of the pulse.
  std::pair<double, double> pulse() {
    const auto p0 = tracer.primary_segments(), b0 = tracer.bounced_segments();
    tracer.compact();  // as the simulation does before each pulse: ended rays are dropped
    tracer.launch(beam, energy);
    tracer.advance(std::numeric_limits<double>::infinity(), deposits);
    return {static_cast<double>(tracer.primary_segments() - p0),
            static_cast<double>(tracer.bounced_segments() - b0)};
  }
};

void run_tracer(benchmark::State& state, const OpticsSpec& spec) {
  TracerPulses run(packing(spheres_of(state)), spec, paper_beam(rays_of(state)));
  double primary = 0, bounced = 0;
  for (auto _ : state) {
    const auto [p, b] = run.pulse();
    primary += p, bounced += b;
  }
  set_counters(state, primary, bounced);
}

// ---- a packing far from the origin -----------------------------------------------------------
// trace/far_frame/<offset m>/<N>/<rays>: the workload (n = 1.4, all bounces) on the packing moved
// by `offset` along every axis, lit from 1000 m upstream when moved (float spacing at 500 m is
// 6e-5 m, a radius at 10^5 spheres). The scene works relative to the packing's centre and takes
// each ray from where it enters the packing's box, so both rows should trace alike.

void run_far_frame(benchmark::State& state, double offset) {
  Particles p = packing(spheres_of(state));
  const Vec3 shift = Vec3::Constant(offset);
  for (Vec3& c : p.centre) c += shift;
  Beam beam = paper_beam(rays_of(state));
  const Vec3 upstream = shift - (offset > 0 ? 1000.0 : 0.0) * beam.direction;
  beam.centre += upstream;
  for (Vec3& o : beam.origin) o += upstream;
  TracerPulses run(p, tracer_spec(true, 1.4, 1000), beam);
  double primary = 0, bounced = 0;
  for (auto _ : state) {
    const auto [a, b] = run.pulse();
    primary += a, bounced += b;
  }
  set_counters(state, primary, bounced);
}

// ---- baseline: Embree's built-in spheres, rtcIntersect1, same outside-hit rule ----------------

struct SkipContext {
  RTCIntersectContext base;
  unsigned skip;
};

// Outside hits only: drop the sphere just left and any exit hit (normal along the ray).
void outside_hit_filter(const RTCFilterFunctionNArguments* args) {
  const auto* ctx = reinterpret_cast<const SkipContext*>(args->context);
  for (unsigned i = 0; i < args->N; ++i) {
    if (args->valid[i] != -1) continue;
    const float dot = RTCHitN_Ng_x(args->hit, args->N, i) * RTCRayN_dir_x(args->ray, args->N, i) +
                      RTCHitN_Ng_y(args->hit, args->N, i) * RTCRayN_dir_y(args->ray, args->N, i) +
                      RTCHitN_Ng_z(args->hit, args->N, i) * RTCRayN_dir_z(args->ray, args->N, i);
    if (RTCHitN_primID(args->hit, args->N, i) == ctx->skip || dot > 0.0f) args->valid[i] = 0;
  }
}

struct BuiltinScene {
  RTCDevice device;
  RTCScene scene;
  explicit BuiltinScene(const Particles& p) {
    device = rtcNewDevice(nullptr);
    scene = rtcNewScene(device);
    RTCGeometry g = rtcNewGeometry(device, RTC_GEOMETRY_TYPE_SPHERE_POINT);
    auto* v = static_cast<float*>(rtcSetNewGeometryBuffer(
        g, RTC_BUFFER_TYPE_VERTEX, 0, RTC_FORMAT_FLOAT4, 4 * sizeof(float), p.size()));
    for (std::size_t i = 0; i < p.size(); ++i) {
      v[4 * i + 0] = static_cast<float>(p.centre[i].x());
      v[4 * i + 1] = static_cast<float>(p.centre[i].y());
      v[4 * i + 2] = static_cast<float>(p.centre[i].z());
      v[4 * i + 3] = static_cast<float>(p.radius[i]);
    }
    rtcCommitGeometry(g);
    // The outside-hit filter goes with the bounced rays' queries only (a context filter): a
    // primary starts upstream of every sphere, so it could never reject a primary's hit, and as
    // a geometry filter it cost the primaries ~8% (a review of these baselines measured it).
    rtcSetSceneFlags(scene, RTC_SCENE_FLAG_CONTEXT_FILTER_FUNCTION);
    rtcAttachGeometry(scene, g);
    rtcReleaseGeometry(g);
    rtcCommitScene(scene);
  }
  ~BuiltinScene() {
    rtcReleaseScene(scene);
    rtcReleaseDevice(device);
  }
};

// Same physics as the tracer (Fresnel (2.25), (3.3), reflection, cutoff), float hits, and the
// same output: what each particle absorbs, added into `deposits` (atomically: the baseline need
// not be deterministic, but it must do the work).
struct Tally {
  double absorbed = 0, escaped = 0, cutoff = 0, primary = 0, bounced = 0;
};

Tally trace_builtin_ray(const BuiltinScene& s, std::vector<double>& deposits, Vec3 o, Vec3 d,
                        double e, double n_hat, int max_bounces) {
  Tally t;
  const double e0 = e;
  unsigned skip = RTC_INVALID_GEOMETRY_ID;
  for (int bounce = 0;; ++bounce) {
    SkipContext ctx;
    rtcInitIntersectContext(&ctx.base);
    ctx.skip = skip;
    if (bounce > 0) ctx.base.filter = outside_hit_filter;
    RTCRayHit rh{};
    rh.ray.org_x = float(o.x()), rh.ray.org_y = float(o.y()), rh.ray.org_z = float(o.z());
    rh.ray.dir_x = float(d.x()), rh.ray.dir_y = float(d.y()), rh.ray.dir_z = float(d.z());
    rh.ray.tnear = 0.0f;
    rh.ray.tfar = std::numeric_limits<float>::infinity();
    rh.ray.mask = 0xFFFFFFFFu;
    rh.hit.geomID = RTC_INVALID_GEOMETRY_ID;
    rtcIntersect1(s.scene, &ctx.base, &rh);
    (bounce == 0 ? t.primary : t.bounced) += 1;
    if (rh.hit.geomID == RTC_INVALID_GEOMETRY_ID) {
      t.escaped += e;
      return t;
    }
    const unsigned i = rh.hit.primID;
    const Vec3 point = o + double(rh.ray.tfar) * d;
    // Embree's own normal (hit point - centre, for its spheres): the sphere's record is what it
    // has just read; the particle arrays' centre would be one more cache miss per hit.
    const Vec3 n = Vec3(rh.hit.Ng_x, rh.hit.Ng_y, rh.hit.Ng_z).normalized();
    const double carried = reflectance(-d.dot(n), n_hat) * e;
    t.absorbed += e - carried;
    std::atomic_ref<double>(deposits[i]).fetch_add(e - carried, std::memory_order_relaxed);
    e = carried;
    d = reflect(d, n).normalized();
    o = point;
    skip = i;
    if (e < 1e-10 * e0 || bounce + 1 >= max_bounces) {
      t.cutoff += e;
      return t;
    }
  }
}

// Items 0 .. count-1 (rays, or packets of 16 rays) in chunks of `chunk` items over TBB;
// trace_ray(k) traces item k and returns its tally. Returns the primary and bounced segments.
template <class TraceRay>
std::pair<double, double> trace_all_rays(std::size_t count, const TraceRay& trace_ray,
                                         std::size_t chunk = 256) {
  std::vector<Tally> chunks((count + chunk - 1) / chunk);
  tbb::parallel_for(tbb::blocked_range<std::size_t>(0, chunks.size(), 1), [&](auto range) {
    for (std::size_t c = range.begin(); c != range.end(); ++c)
      for (std::size_t k = c * chunk; k < std::min(count, (c + 1) * chunk); ++k) {
        const Tally t = trace_ray(k);
        chunks[c].primary += t.primary;
        chunks[c].bounced += t.bounced;
      }
  });
  double primary = 0, bounced = 0;
  for (const Tally& t : chunks) primary += t.primary, bounced += t.bounced;
  return {primary, bounced};
}

template <class TraceRay>
void run_rays(benchmark::State& state, const Beam& beam, const TraceRay& trace_ray) {
  double primary = 0, bounced = 0;
  for (auto _ : state) {
    const auto [p, b] = trace_all_rays(beam.size(), trace_ray);
    primary += p, bounced += b;
  }
  set_counters(state, primary, bounced);
}

// One pulse at a time through the plain rtcIntersect1 loop over Embree's built-in spheres.
struct BuiltinPulses {
  const Particles& p;
  const BuiltinScene scene;
  mutable std::vector<double> deposits;  // J per particle, added to by every pulse
  const Beam& beam;
  const std::vector<double> energy;
  const double upstream;  // the start plane, upstream of every sphere
  double n_hat;
  int max_bounces;
  BuiltinPulses(const Particles& p, const Beam& beam, double n_hat, int max_bounces)
      : p(p),
        scene(p),
        deposits(p.size(), 0.0),
        beam(beam),
        energy(beam.ray_energies(1e-9)),
        upstream(-2.0 * p.max_radius()),
        n_hat(n_hat),
        max_bounces(max_bounces) {}
  Tally ray(std::size_t k) const {
    return trace_builtin_ray(scene, deposits, beam.origin[k] + upstream * beam.direction,
                             beam.direction, energy[k], n_hat, max_bounces);
  }
  std::pair<double, double> pulse() const {
    return trace_all_rays(beam.size(), [this](std::size_t k) { return ray(k); });
  }
};

// Embree's own packets on this scene: its built-in spheres in the tracer's coherent 16-ray tiles
// (consecutive beam rays), rtcIntersect16, then the same Fresnel step and deposit per hit as the
// single-ray loop. Float hits, no callback: what Embree's packets alone gain here.

// The packet of beam rays [first, first + 16) as the single-ray loop starts them; lanes past the
// beam's end repeat its last ray and are invalid. Returns the number of valid lanes.
std::size_t beam_packet(const Beam& beam, double upstream, std::size_t first, RTCRayHit16& rh,
                        int* valid) {
  const std::size_t count = std::min<std::size_t>(16, beam.size() - first);
  for (std::size_t i = 0; i < 16; ++i) {
    const std::size_t k = first + std::min(i, count - 1);
    const Vec3 o = beam.origin[k] + upstream * beam.direction;
    valid[i] = i < count ? -1 : 0;
    rh.ray.org_x[i] = float(o.x()), rh.ray.org_y[i] = float(o.y()), rh.ray.org_z[i] = float(o.z());
    rh.ray.dir_x[i] = float(beam.direction.x()), rh.ray.dir_y[i] = float(beam.direction.y());
    rh.ray.dir_z[i] = float(beam.direction.z());
    rh.ray.tnear[i] = 0.0f;
    rh.ray.tfar[i] = std::numeric_limits<float>::infinity();
    rh.ray.mask[i] = 0xFFFFFFFFu;
    rh.hit.geomID[i] = RTC_INVALID_GEOMETRY_ID;
  }
  return count;
}

void intersect_coherent(const BuiltinScene& s, const int* valid, RTCRayHit16& rh) {
  RTCIntersectContext ctx;
  rtcInitIntersectContext(&ctx);
  ctx.flags = RTC_INTERSECT_CONTEXT_FLAG_COHERENT;
  rtcIntersect16(valid, s.scene, &ctx, &rh);
}

Tally trace_builtin_packet(const BuiltinScene& s, std::vector<double>& deposits, const Beam& beam,
                           const std::vector<double>& energy, double upstream, std::size_t first,
                           double n_hat) {
  alignas(64) RTCRayHit16 rh{};
  alignas(64) int valid[16];
  const std::size_t count = beam_packet(beam, upstream, first, rh, valid);
  intersect_coherent(s, valid, rh);
  Tally t;
  for (std::size_t i = 0; i < count; ++i) {
    t.primary += 1;
    const double e = energy[first + i];
    if (rh.hit.geomID[i] == RTC_INVALID_GEOMETRY_ID) {
      t.escaped += e;
      continue;
    }
    const Vec3 d = beam.direction;
    const Vec3 n = Vec3(rh.hit.Ng_x[i], rh.hit.Ng_y[i], rh.hit.Ng_z[i]).normalized();
    const double carried = reflectance(-d.dot(n), n_hat) * e;
    t.absorbed += e - carried;
    std::atomic_ref<double>(deposits[rh.hit.primID[i]])
        .fetch_add(e - carried, std::memory_order_relaxed);
    t.cutoff += carried;
  }
  return t;
}

// The packets must find the single rays' hits: every ray of the beam traced both ways, its hit
// (sphere or miss) compared. Embree's packet and single-ray kernels round differently, so a ray
// grazing a sphere's float edge may part them: the check allows none.
bool packets_match_single_rays(const BuiltinPulses& run) {
  for (std::size_t first = 0; first < run.beam.size(); first += 16) {
    alignas(64) RTCRayHit16 packet{};
    alignas(64) int valid[16];
    const std::size_t count = beam_packet(run.beam, run.upstream, first, packet, valid);
    intersect_coherent(run.scene, valid, packet);
    for (std::size_t i = 0; i < count; ++i) {
      RTCRayHit single{};
      single.ray.org_x = packet.ray.org_x[i], single.ray.org_y = packet.ray.org_y[i];
      single.ray.org_z = packet.ray.org_z[i];
      single.ray.dir_x = packet.ray.dir_x[i], single.ray.dir_y = packet.ray.dir_y[i];
      single.ray.dir_z = packet.ray.dir_z[i];
      single.ray.tfar = std::numeric_limits<float>::infinity();
      single.ray.mask = 0xFFFFFFFFu;
      single.hit.geomID = RTC_INVALID_GEOMETRY_ID;
      RTCIntersectContext ctx;
      rtcInitIntersectContext(&ctx);
      rtcIntersect1(run.scene.scene, &ctx, &single);
      if (single.hit.geomID != packet.hit.geomID[i] ||
          (single.hit.geomID != RTC_INVALID_GEOMETRY_ID &&
           single.hit.primID != packet.hit.primID[i]))
        return false;
    }
  }
  return true;
}

void run_builtin_packets(benchmark::State& state) {
  const BuiltinPulses run(packing(spheres_of(state)), paper_beam(rays_of(state)), 1.4, 1);
  if (!packets_match_single_rays(run)) {
    state.SkipWithError("built-in spheres: packets and single rays hit different spheres");
    return;
  }
  const std::size_t packets = (run.beam.size() + 15) / 16;
  double primary = 0;
  for (auto _ : state)
    primary += trace_all_rays(
                   packets,
                   [&](std::size_t k) {
      return trace_builtin_packet(run.scene, run.deposits, run.beam, run.energy, run.upstream,
                                  16 * k, 1.4);
                   },
                   16)
        .first;
  set_counters(state, primary, 0.0);
}

void run_builtin(benchmark::State& state, double n_hat, int max_bounces) {
  const BuiltinPulses run(packing(spheres_of(state)), paper_beam(rays_of(state)), n_hat,
                          max_bounces);
  run_rays(state, run.beam, [&](std::size_t k) { return run.ray(k); });
}

// ---- paired: this tracer against the built-in loop, pulse by pulse ---------------------------
// trace/paired/<primary|n14|n200>/<N>/<rays>: each iteration traces one pulse with each, in
// alternating order, and `ratio` is the median of the pairs' time ratios (built-in / tracer).
// A shared machine's speed drifts by tens of percent over seconds; the two halves of a pair see
// the same machine, so the ratio holds still where the separate rows' medians do not.

template <class Pulse>
double seconds_of(Pulse&& pulse) {
  const auto start = std::chrono::steady_clock::now();
  benchmark::DoNotOptimize(pulse());
  return std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
}

double median(std::vector<double> v) {
  std::nth_element(v.begin(), v.begin() + v.size() / 2, v.end());
  return v[v.size() / 2];
}

void run_paired(benchmark::State& state, double n_hat, int max_bounces,
                bool reuse_primaries = false) {
  const Particles& p = packing(spheres_of(state));
  const Beam& beam = paper_beam(rays_of(state));
  OpticsSpec spec = tracer_spec(true, n_hat, max_bounces);
  spec.reuse_primaries = reuse_primaries;
  TracerPulses tracer(p, spec, beam);
  const BuiltinPulses builtin(p, beam, n_hat, max_bounces);
  tracer.pulse(), builtin.pulse();  // warm: first-touch pages, caches (and the first hits to reuse)
  std::vector<double> ratio, t_tracer, t_builtin;
  for (auto _ : state) {
    const bool tracer_first = ratio.size() % 2 == 0;
    double a = 0, b = 0;
    if (tracer_first) a = seconds_of([&] { return tracer.pulse(); });
    b = seconds_of([&] { return builtin.pulse(); });
    if (!tracer_first) a = seconds_of([&] { return tracer.pulse(); });
    t_tracer.push_back(a), t_builtin.push_back(b), ratio.push_back(b / a);
  }
  state.counters["ratio"] = median(ratio);
  state.counters["ratio_min"] = *std::min_element(ratio.begin(), ratio.end());
  state.counters["tracer_ms"] = 1e3 * median(t_tracer);
  state.counters["builtin_ms"] = 1e3 * median(t_builtin);
}

// ---- baseline: brute force over every sphere ------------------------------------------------

// Segments only (the brute-force loop is a speed baseline): nearest outside hit over all spheres.
Tally trace_brute_ray(const Particles& p, Vec3 o, Vec3 d, double e, double n_hat) {
  Tally t;
  const double e0 = e;
  std::uint32_t skip = kNoParticle;
  for (int bounce = 0; bounce < 1000; ++bounce) {
    (bounce == 0 ? t.primary : t.bounced) += 1;
    double best = kNoHit;
    std::uint32_t who = kNoParticle;
    for (std::uint32_t i = 0; i < p.size(); ++i) {
      if (i == skip) continue;
      const double hit = ray_sphere_entry(o, d, p.centre[i], p.radius[i]);
      if (hit < best) best = hit, who = i;
    }
    if (who == kNoParticle) break;
    const Vec3 point = o + best * d;
    const Vec3 n = (point - p.centre[who]).normalized();
    const double carried = reflectance(-d.dot(n), n_hat) * e;
    if (carried < 1e-10 * e0) break;
    e = carried, d = reflect(d, n).normalized(), o = point, skip = who;
  }
  return t;
}

void run_brute(benchmark::State& state, double n_hat) {
  const Particles& p = packing(spheres_of(state));
  const Beam& beam = paper_beam(rays_of(state));
  const auto energy = beam.ray_energies(1e-9);
  const double upstream = -2.0 * p.max_radius();
  run_rays(state, beam, [&](std::size_t k) {
    return trace_brute_ray(p, beam.origin[k] + upstream * beam.direction, beam.direction, energy[k],
                           n_hat);
  });
}

// ---- scene updates --------------------------------------------------------------------------

// 1% of the spheres: uniformly at random, or the 1% nearest the beam's entry (where vaporisation
// actually happens: a compact region, which is what spatial bricks exploit). With `rounds`, that
// many such sets one after another (under the beam: the next layer in, as a burn front goes).
std::vector<std::uint32_t> victims(const Particles& p, bool under_beam, std::size_t rounds = 1) {
  const std::size_t count = rounds * (p.size() / 100);
  std::vector<std::uint32_t> ids(p.size());
  std::iota(ids.begin(), ids.end(), 0u);
  if (under_beam) {
    auto key = [&](std::uint32_t i) {
      const Vec3& c = p.centre[i];
      return c.x() + std::hypot(c.y() - 0.5 * kD, c.z() - 0.5 * kD);
    };
    std::partial_sort(ids.begin(), ids.begin() + count, ids.end(),
                      [&](auto a, auto b) { return key(a) < key(b); });
  } else {
    Rng rng(99);
    for (std::size_t k = 0; k < count; ++k) std::swap(ids[k], ids[k + rng.next() % (p.size() - k)]);
  }
  ids.resize(count);
  return ids;
}

// Times remove(owner, ids) alone: the owner is made (make()) and destroyed outside the timing.
template <class Make, class Remove>
void time_removal(benchmark::State& state, bool under_beam, Make make, Remove remove) {
  const auto ids = victims(packing(static_cast<std::size_t>(state.range(0))), under_beam);
  for (auto _ : state) {
    state.PauseTiming();
    auto owner = make();
    state.ResumeTiming();
    remove(*owner, ids);
    state.PauseTiming();
    owner.reset();
    state.ResumeTiming();
  }
  state.counters["removed"] = static_cast<double>(ids.size());
}

void run_update(benchmark::State& state, SceneUpdate mode, bool under_beam) {
  const Particles& p = packing(static_cast<std::size_t>(state.range(0)));
  time_removal(
      state, under_beam, [&] { return std::make_unique<EmbreeScene>(p, mode); },
      [](EmbreeScene& scene, const auto& ids) { scene.remove(ids); });
}

// A tracer over `p`, updating its scene by `mode`, with a pulse of the paper's beam in flight
// inside the packing.
std::unique_ptr<Tracer> tracer_in_flight(const Particles& p, SceneUpdate mode) {
  OpticsSpec spec;
  spec.scene_update = mode;
  auto tracer = std::make_unique<Tracer>(p, spec);
  tracer->launch(paper_beam(), 1e-9);
  std::vector<double> deposits;
  tracer->advance(2e-4, deposits);
  return tracer;
}

// What the driver pays: Tracer::remove_particles (scene + grid masks, rays heading for a removed
// sphere retraced later) with a pulse in flight.
void run_tracer_remove(benchmark::State& state, bool under_beam) {
  const Particles& p = packing(static_cast<std::size_t>(state.range(0)));
  time_removal(
      state, under_beam, [&] { return tracer_in_flight(p, OpticsSpec{}.scene_update); },
      [](Tracer& tracer, const auto& ids) { tracer.remove_particles(ids); });
}

// A run's updates in a row: eleven removals of 1% each, the eleventh past the rebuild threshold
// (10% of N), for the scene alone and for the tracer with a pulse in flight. Manual time: the
// slowest of the eleven, what one time step waits for at worst; mean_ms: their mean. Deferred's
// slowest is its synchronous rebuild; background's is the update that starts its build.
template <class Make, class Remove, class Rebuilds>
void time_update_sequence(benchmark::State& state, bool under_beam, Make make, Remove remove,
                          Rebuilds rebuilds) {
  constexpr std::size_t kRounds = 11;
  const auto ids = victims(packing(static_cast<std::size_t>(state.range(0))), under_beam, kRounds);
  const std::size_t count = ids.size() / kRounds;
  double sum = 0.0;
  std::size_t updates = 0;
  std::vector<double> each(kRounds, 0.0);
  double started = 0.0;
  for (auto _ : state) {
    auto owner = make();  // manual time: made and destroyed untimed
    double worst = 0.0;
    for (std::size_t k = 0; k < kRounds; ++k) {
      const auto start = std::chrono::steady_clock::now();
      remove(*owner, std::span<const std::uint32_t>(ids.data() + k * count, count));
      const double took =
          std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
      worst = std::max(worst, took), sum += took, ++updates;
      each[k] = std::max(each[k], took);
    }
    state.SetIterationTime(worst);
    started += static_cast<double>(rebuilds(*owner));
    owner.reset();  // background: stops the build in flight
  }
  state.counters["mean_ms"] = 1e3 * sum / static_cast<double>(updates);
  // The slowest of each update over the iterations: the 11th crosses the threshold (10 x 1% is
  // 10% of N, not past it).
  for (std::size_t k = 9; k < kRounds; ++k)
    state.counters["update" + std::to_string(k + 1) + "_ms"] = 1e3 * each[k];
  state.counters["removed_each"] = static_cast<double>(count);
  // Builds started per sequence: background puts one off while its first spare copy's pages are
  // still being touched (they are, removals a few ms apart); it starts at a later poll.
  state.counters["rebuilds"] = started / static_cast<double>(state.iterations());
}

void run_update_sequence(benchmark::State& state, SceneUpdate mode, bool under_beam) {
  const Particles& p = packing(static_cast<std::size_t>(state.range(0)));
  time_update_sequence(
      state, under_beam, [&] { return std::make_unique<EmbreeScene>(p, mode); },
      [](EmbreeScene& scene, auto ids) { scene.remove(ids); },
      [](const EmbreeScene& scene) { return scene.rebuilds(); });
}

void run_tracer_update_sequence(benchmark::State& state, SceneUpdate mode, bool under_beam) {
  const Particles& p = packing(static_cast<std::size_t>(state.range(0)));
  time_update_sequence(
      state, under_beam, [&] { return tracer_in_flight(p, mode); },
      [](Tracer& tracer, auto ids) { tracer.remove_particles(ids); },
      [](const Tracer& tracer) { return tracer.scene_rebuilds(); });
}

// What a rebuild costs the run, not the update alone: removing 11% at random (past the
// threshold), then range(1) pulses (the paper's beam, 10^4 rays, n = 1.4, all bounces; ~9 ms
// each at 1e6), then the rebuild finished. Deferred rebuilds before the pulses; background
// builds during them, on the same two cores. (Measured: the background build confined to its own
// thread, a one-thread TBB arena, took twice as long, ~0.8 s; at nice 19 no better.)
void run_pulse_with_rebuild(benchmark::State& state, SceneUpdate mode) {
  const Particles& p = packing(static_cast<std::size_t>(state.range(0)));
  const auto ids = victims(p, false, 11);
  for (auto _ : state) {
    state.PauseTiming();
    auto run = std::make_unique<TracerPulses>(p, tracer_spec(true, 1.4, 1000, mode), paper_beam());
    state.ResumeTiming();
    run->tracer.remove_particles(ids);
    for (long k = 0; k < state.range(1); ++k) run->pulse();
    run->tracer.finish_scene_rebuild();
    state.PauseTiming();
    if (run->tracer.scene_rebuilds() != 1) state.SkipWithError("expected one rebuild");
    run.reset();  // the tracer's teardown, untimed
    state.ResumeTiming();
  }
}

void run_build(benchmark::State& state, SceneUpdate mode) {
  const Particles& p = packing(static_cast<std::size_t>(state.range(0)));
  for (auto _ : state) {
    EmbreeScene scene(p, mode);
    benchmark::DoNotOptimize(&scene);
  }
}

// BEAMPACK_BENCH_MIN_TIME=s: seconds per benchmark (default 0.3).
double min_time() {
  const char* s = std::getenv("BEAMPACK_BENCH_MIN_TIME");
  return s ? std::atof(s) : 0.3;
}

// Arguments: spheres, rays. The size ladder with 10^4 rays throughout and with the paper's
// resolution (paper_resolution_rays); at 1e6 spheres also the paper's own N_r = 1000 rays.
void sizes(benchmark::internal::Benchmark* b) {
  for (long n : {1000L, 10000L, 100000L, 1000000L}) {
    b->Args({n, static_cast<long>(kRays)});
    if (paper_resolution_rays(n) != kRays)
      b->Args({n, static_cast<long>(paper_resolution_rays(n))});
  }
  b->Args({1000000L, 1000L});
  b->Unit(benchmark::kMillisecond)->MinTime(min_time())->UseRealTime();
  // With --benchmark_repetitions: the least repetition besides mean, median and stddev. On a
  // shared VM the noise only ever adds time, so the least is the estimate of the undisturbed run.
  b->ComputeStatistics(
      "min", [](const std::vector<double>& v) { return *std::min_element(v.begin(), v.end()); });
}

// The size ladder with 10^4 rays only: the slower design alternatives.
void sizes_fixed_rays(benchmark::internal::Benchmark* b) {
  for (long n : {1000L, 10000L, 100000L, 1000000L}) b->Args({n, static_cast<long>(kRays)});
  b->Unit(benchmark::kMillisecond)->MinTime(min_time())->UseRealTime();
}

// 1e5 and 1e6 spheres, 10^4 rays: the design comparisons (scene modes, clusters, grid settings).
void large(benchmark::internal::Benchmark* b) {
  for (long n : {100000L, 1000000L}) b->Args({n, static_cast<long>(kRays)});
  b->Unit(benchmark::kMillisecond)->MinTime(min_time())->UseRealTime();
}

// The paired rows: 1e5 and 1e6 spheres, 10^4 rays and the paper's resolution.
void paired_sizes(benchmark::internal::Benchmark* b) {
  for (long n : {100000L, 1000000L})
    for (long rays : {static_cast<long>(kRays), static_cast<long>(paper_resolution_rays(n))})
      b->Args({n, rays});
  b->Unit(benchmark::kMillisecond)->UseRealTime();
}

// 1e7 spheres (about 3 GB with the scene and the grid): the top of the size ladder, a few
// iterations only, so a full run stays within minutes.
void huge(benchmark::internal::Benchmark* b) {
  b->Args({10'000'000, static_cast<long>(kRays)})
      ->Unit(benchmark::kMillisecond)
      ->Iterations(3)
      ->UseRealTime();
}

// ---- grid walk: one ray at a time against interleaved walks ---------------------------------
// trace/grid_batch/<variant>/<N>: 10^4 bounced rays (each leaves a random sphere outward, that
// sphere skipped, no distance limit) through SphereGrid::intersect1 one by one (`single`) or
// intersect_many in batches of 256 (`many`). Answers whether overlapping the cache misses of
// several walks pays at 10^6 spheres, where the walk is bound by memory latency.

struct BouncedRays {
  std::vector<Vec3> origin, direction;
  std::vector<std::uint32_t> skip;
};

Vec3 random_unit(Rng& rng) {
  for (;;) {  // rejection from the cube: isotropic without trigonometry
    const Vec3 u(rng.uniform(-1, 1), rng.uniform(-1, 1), rng.uniform(-1, 1));
    const double n2 = u.squaredNorm();
    if (n2 > 1e-6 && n2 <= 1.0) return u / std::sqrt(n2);
  }
}

BouncedRays bounced_rays(const Particles& p, std::size_t count) {
  BouncedRays rays;
  Rng rng(31);
  for (std::size_t k = 0; k < count; ++k) {
    const auto i = static_cast<std::uint32_t>(rng.next() % p.size());
    const Vec3 n = random_unit(rng);
    Vec3 d = random_unit(rng);
    if (d.dot(n) < 0.0) d = -d;  // outward, as a reflection leaves the surface
    rays.origin.push_back(p.centre[i] + p.radius[i] * n);
    rays.direction.push_back(d);
    rays.skip.push_back(i);
  }
  return rays;
}

const SphereGrid& grid_of(std::size_t n) {
  static std::map<std::size_t, std::unique_ptr<SphereGrid>> cache;
  auto& slot = cache[n];
  if (!slot) slot = std::make_unique<SphereGrid>(packing(n), OpticsSpec{}.grid_cell_factor);
  return *slot;
}

void run_grid_batch(benchmark::State& state, bool many) {
  const auto n = static_cast<std::size_t>(state.range(0));
  const SphereGrid& grid = grid_of(n);
  const BouncedRays rays = bounced_rays(packing(n), kRays);
  std::vector<double> t(kRays);
  std::vector<std::uint32_t> hit(kRays), ids(kRays);
  std::vector<Vec3> normal(kRays);
  std::iota(ids.begin(), ids.end(), 0u);
  const RayQuery q{rays.origin.data(), rays.direction.data(), rays.skip.data(), t.data(),
                   hit.data(),         normal.data()};
  constexpr std::size_t kBatch = 256;
  for (auto _ : state) {
    std::fill(t.begin(), t.end(), kNoHit);
    std::fill(hit.begin(), hit.end(), kNoParticle);
    if (many) {
      for (std::size_t k = 0; k < kRays; k += kBatch)
        grid.intersect_many(q, std::span(ids).subspan(k, std::min(kBatch, kRays - k)));
    } else {
      for (std::uint32_t r = 0; r < kRays; ++r) grid.intersect1(q, r);
    }
    benchmark::DoNotOptimize(t.data());
    benchmark::ClobberMemory();
  }
  state.counters["time/ray"] =
      benchmark::Counter(static_cast<double>(kRays), benchmark::Counter::kIsIterationInvariantRate |
                                                         benchmark::Counter::kInvert);
  state.counters["hit_fraction"] =
      static_cast<double>(
          std::count_if(hit.begin(), hit.end(), [](std::uint32_t p) { return p != kNoParticle; })) /
      kRays;
}

void register_grid_batch() {
  for (bool many : {false, true})
    benchmark::RegisterBenchmark(many ? "trace/grid_batch/many" : "trace/grid_batch/single",
                                 [many](benchmark::State& s) { run_grid_batch(s, many); })
        ->Arg(100000)
        ->Arg(1000000)
        ->Unit(benchmark::kMicrosecond)
        ->MinTime(min_time())
        ->UseRealTime();
}

void register_all() {
  for (double n_hat : {1.4, 20.0}) {
    const std::string large = "/n" + std::to_string(static_cast<int>(std::lround(n_hat * 10)));
    benchmark::RegisterBenchmark(("trace/workload/tracer_packets" + large).c_str(),
                                 [=](benchmark::State& s) {
      run_tracer(s, tracer_spec(true, n_hat, 1000));
    })->Apply(huge);
    benchmark::RegisterBenchmark(("trace/workload/builtin_sphere" + large).c_str(),
                                 [=](benchmark::State& s) {
      run_builtin(s, n_hat, 1000);
    })->Apply(huge);
  }
  for (double n_hat : {1.4, 20.0}) {
    const std::string tag = "/n" + std::to_string(static_cast<int>(std::lround(n_hat * 10)));
    benchmark::RegisterBenchmark(("trace/workload/tracer_packets" + tag).c_str(),
                                 [=](benchmark::State& s) {
      run_tracer(s, tracer_spec(true, n_hat, 1000));
    })->Apply(sizes);
    benchmark::RegisterBenchmark(("trace/workload/tracer_packets_embree_bounces" + tag).c_str(),
                                 [=](benchmark::State& s) {
      run_tracer(
          s, tracer_spec(true, n_hat, 1000, OpticsSpec{}.scene_update, 1, BounceSearch::embree));
    })->Apply(sizes_fixed_rays);
    benchmark::RegisterBenchmark(("trace/workload/tracer_packets_packet_bounces" + tag).c_str(),
                                 [=](benchmark::State& s) {
      run_tracer(
          s, tracer_spec(true, n_hat, 1000, OpticsSpec{}.scene_update, 1, BounceSearch::packets));
    })->Apply(sizes_fixed_rays);
    benchmark::RegisterBenchmark(("trace/workload/tracer_single" + tag).c_str(),
                                 [=](benchmark::State& s) {
      run_tracer(
          s, tracer_spec(false, n_hat, 1000, OpticsSpec{}.scene_update, 1, BounceSearch::embree));
    })->Apply(sizes_fixed_rays);
    benchmark::RegisterBenchmark(("trace/workload/builtin_sphere" + tag).c_str(),
                                 [=](benchmark::State& s) {
      run_builtin(s, n_hat, 1000);
    })->Apply(sizes);
    benchmark::RegisterBenchmark(("trace/workload/brute_force" + tag).c_str(),
                                 [=](benchmark::State& s) { run_brute(s, n_hat); })
        ->Args({1000, static_cast<long>(kRays)})
        ->Unit(benchmark::kMillisecond)
        ->MinTime(min_time())
        ->UseRealTime();
  }
  // The scene's update mode decides its build (static SAH for mask_only/rebuild, two-level
  // low quality for refit/bricks), hence its tracing speed too.
  for (const auto& [name, mode] :
       {std::pair{"deferred", SceneUpdate::deferred}, std::pair{"refit", SceneUpdate::refit},
        std::pair{"bricks", SceneUpdate::bricks}})
    benchmark::RegisterBenchmark(("trace/scene_mode/" + std::string(name) + "/n200").c_str(),
                                 [mode = mode](benchmark::State& s) {
      run_tracer(s, tracer_spec(true, 20.0, 1000, mode));
    })->Apply(large);
  for (const auto& [name, mode] :
       {std::pair{"deferred", SceneUpdate::deferred}, std::pair{"bricks", SceneUpdate::bricks}})
    benchmark::RegisterBenchmark(("trace/scene_mode/" + std::string(name) + "/primary").c_str(),
                                 [mode = mode](benchmark::State& s) {
      run_tracer(s, tracer_spec(true, 20.0, 1, mode));
    })->Apply(large);
  // Embree primitive = a cluster of K consecutive (Morton) spheres: fewer callbacks, looser boxes.
  for (unsigned k : {1u, 2u, 4u, 8u}) {
    benchmark::RegisterBenchmark(("trace/cluster/k" + std::to_string(k) + "/n200").c_str(),
                                 [k](benchmark::State& s) {
      run_tracer(s, tracer_spec(true, 20.0, 1000, SceneUpdate::deferred, k));
    })->Apply(large);
    benchmark::RegisterBenchmark(("trace/cluster/k" + std::to_string(k) + "/primary").c_str(),
                                 [k](benchmark::State& s) {
      run_tracer(s, tracer_spec(true, 20.0, 1, SceneUpdate::deferred, k));
    })->Apply(large);
  }
  for (double f : {1.5, 2.0, 3.0, 4.0})
    benchmark::RegisterBenchmark(("trace/grid_cell/" + std::to_string(f).substr(0, 3) + "R/n200")
                                     .c_str(),
                                 [f](benchmark::State& s) {
      run_tracer(
          s, tracer_spec(true, 20.0, 1000, OpticsSpec{}.scene_update, 1, BounceSearch::grid, f));
    })->Apply(large);
  // Primaries traced every pulse (the tracing speed), and reused from the pulse before (what a
  // run with a repeated beam pays: OpticsSpec::reuse_primaries).
  for (bool reuse : {false, true}) {
    const std::string tag = reuse ? "_reused" : "";
    benchmark::RegisterBenchmark(("trace/paired/primary" + tag).c_str(),
                                 [reuse](benchmark::State& s) { run_paired(s, 1.4, 1, reuse); })
        ->Apply(paired_sizes)
        ->Iterations(41);
    for (double n_hat : {1.4, 20.0})
      benchmark::RegisterBenchmark(
          ("trace/paired/n" + std::to_string(static_cast<int>(std::lround(n_hat * 10))) + tag)
              .c_str(),
          [n_hat, reuse](benchmark::State& s) { run_paired(s, n_hat, 1000, reuse); })
          ->Apply(paired_sizes)
          ->Iterations(9);
  }
  for (double offset : {0.0, 500.0})
    benchmark::RegisterBenchmark(
        ("trace/far_frame/" + std::to_string(static_cast<int>(offset))).c_str(),
        [offset](benchmark::State& s) { run_far_frame(s, offset); })
        ->Args({100000, static_cast<long>(kRays)})
        ->Unit(benchmark::kMillisecond)
        ->MinTime(min_time())
        ->UseRealTime();
  benchmark::RegisterBenchmark("trace/primary/tracer_packets", [](benchmark::State& s) {
    run_tracer(s, tracer_spec(true, 1.4, 1));
  })->Apply(sizes);
  benchmark::RegisterBenchmark("trace/primary/tracer_single", [](benchmark::State& s) {
    run_tracer(s, tracer_spec(false, 1.4, 1, OpticsSpec{}.scene_update, 1, BounceSearch::embree));
  })->Apply(sizes);
  benchmark::RegisterBenchmark("trace/primary/builtin_sphere", [](benchmark::State& s) {
    run_builtin(s, 1.4, 1);
  })->Apply(sizes);
  benchmark::RegisterBenchmark("trace/primary/builtin_sphere_packets", [](benchmark::State& s) {
    run_builtin_packets(s);
  })->Apply(sizes);
  const std::pair<const char*, SceneUpdate> modes[] = {
      {"deferred", SceneUpdate::deferred},   {"background", SceneUpdate::background},
      {"mask_only", SceneUpdate::mask_only}, {"rebuild", SceneUpdate::rebuild},
      {"refit", SceneUpdate::refit},         {"bricks", SceneUpdate::bricks}};
  for (bool beam : {false, true})
    benchmark::RegisterBenchmark((std::string("scene_update/tracer_remove_particles") +
                                  (beam ? "/beam_1pct" : "/random_1pct"))
                                     .c_str(),
                                 [beam](benchmark::State& s) { run_tracer_remove(s, beam); })
        ->Arg(100000)
        ->Arg(1000000)
        ->Unit(benchmark::kMillisecond)
        ->Iterations(5)
        ->UseRealTime();
  for (const auto& [name, mode] : {std::pair{"deferred", SceneUpdate::deferred},
                                   std::pair{"background", SceneUpdate::background}}) {
    for (bool beam : {false, true}) {
      const std::string where = beam ? "/beam_11x1pct" : "/random_11x1pct";
      benchmark::RegisterBenchmark(
          ("scene_update/sequence/" + std::string(name) + where).c_str(),
          [mode = mode, beam](benchmark::State& s) { run_update_sequence(s, mode, beam); })
          ->Arg(100000)
          ->Arg(1000000)
          ->Unit(benchmark::kMillisecond)
          ->Iterations(3)
          ->UseManualTime();
      benchmark::RegisterBenchmark(
          ("scene_update/sequence/tracer_" + std::string(name) + where).c_str(),
          [mode = mode, beam](benchmark::State& s) { run_tracer_update_sequence(s, mode, beam); })
          ->Arg(1000000)
          ->Unit(benchmark::kMillisecond)
          ->Iterations(3)
          ->UseManualTime();
    }
    benchmark::RegisterBenchmark(
        ("scene_update/pulse_with_rebuild/" + std::string(name)).c_str(),
        [mode = mode](benchmark::State& s) { run_pulse_with_rebuild(s, mode); })
        ->Args({1000000, 1})
        ->Args({1000000, 6})
        ->Unit(benchmark::kMillisecond)
        ->Iterations(3)
        ->UseRealTime();
  }
  for (const auto& [name, mode] : modes) {
    for (bool beam : {false, true}) {
      const std::string label =
          std::string("scene_update/") + name + (beam ? "/beam_1pct" : "/random_1pct");
      benchmark::RegisterBenchmark(
          label.c_str(), [mode = mode, beam](benchmark::State& s) { run_update(s, mode, beam); })
          ->Arg(100000)
          ->Arg(1000000)
          ->Unit(benchmark::kMillisecond)
          ->Iterations(5)
          ->UseRealTime();
    }
    benchmark::RegisterBenchmark((std::string("scene_update/build/") + name).c_str(),
                                 [mode = mode](benchmark::State& s) { run_build(s, mode); })
        ->Arg(1000000)
        ->Unit(benchmark::kMillisecond)
        ->Iterations(3)
        ->UseRealTime();
  }
  register_grid_batch();
}

// BEAMPACK_BENCH_THREADS=k limits TBB (Embree builds and the tracers) to k threads: with other
// jobs on the machine, one thread gives steadier side-by-side ratios.
std::unique_ptr<tbb::global_control> thread_limit() {
  const char* k = std::getenv("BEAMPACK_BENCH_THREADS");
  if (!k) return nullptr;
  return std::make_unique<tbb::global_control>(tbb::global_control::max_allowed_parallelism,
                                               static_cast<std::size_t>(std::atoi(k)));
}

const auto limit = thread_limit();
const bool registered = (register_all(), true);

}  // namespace
}  // namespace beampack
