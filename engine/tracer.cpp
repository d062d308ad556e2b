#include "engine/tracer.h"

#include "engine/float_mode.h"

#include <tbb/blocked_range.h>
#include <tbb/global_control.h>
#include <tbb/parallel_for.h>
#include <tbb/parallel_pipeline.h>
#include <tbb/task_arena.h>
#include <tbb/task_group.h>

#include <Eigen/Geometry>
#include <algorithm>
#include <array>
#include <bitset>
#include <cmath>
#include <numbers>
#include <numeric>
#include <sstream>
#include <string>
#include <utility>

#include "engine/fresnel.h"
#include "geometry/check.h"
#include "geometry/compensated_sum.h"
#include "geometry/error.h"
#include "geometry/packing.h"
#include "geometry/ray_sphere.h"

namespace beampack {
namespace {

// Rays are stepped in chunks of OpticsSpec::chunk_rays (at most kMaxChunkRays), and a chunk whose
// rays are all in free flight through an advance is left alone. The chunks an advance runs go to
// the threads in items of kBatchRays rays or more. No size changes a result: the events are
// summed in ray order whatever the chunks and items.
constexpr std::size_t kBatchRays = 256;
constexpr std::size_t kPacket = 16;
constexpr std::size_t kBatchesInFlight = 16;  // batches traced ahead of the in-order reduction
constexpr std::size_t kItemsPerThread = 16;
constexpr double kInf = std::numeric_limits<double>::infinity();

std::string optics_text(const MaterialOptics& m) {
  std::ostringstream s;
  s << "`optics.n_solid` = " << m.n_solid.real() << ", `optics.k_solid` = " << m.n_solid.imag()
    << ", `optics.n_liquid` = " << m.n_liquid.real()
    << ", `optics.k_liquid` = " << m.n_liquid.imag() << ", `optics.mu_hat` = " << m.mu_hat;
  return s.str();
}

// Rays start upstream of the whole packing and its hits are found in double precision from
// there: a packing spanning more than kMaxSpanRadii of its smallest radii leaves a grazing hit
// under ~1e-4 R of its digits (one stray row at x = 1e20 m among spheres of 0.01 m: every ray
// missed, silently; at 1e13 m absorption was off by 1e-8), and its float bounds long before that
// are padded by many radii (slow, still exact).
constexpr double kMaxSpanRadii = 1e12;

void check_span(const Particles& p) {
  const Box box = p.bounds();  // live particles
  if (box.empty()) return;
  int axis = 0;
  const double span = (box.upper - box.lower).maxCoeff(&axis);
  double r_min = std::numeric_limits<double>::infinity();
  std::size_t low = p.size(), high = p.size(), smallest = p.size();
  for (std::size_t i = 0; i < p.size(); ++i) {
    if (!p.alive[i] || !(p.radius[i] > 0.0)) continue;  // r <= 0: removed (the scene's rule)
    if (p.radius[i] < r_min) r_min = p.radius[i], smallest = i;
    if (low == p.size() || p.centre[i][axis] - p.radius[i] < p.centre[low][axis] - p.radius[low])
      low = i;
    if (high == p.size() || p.centre[i][axis] + p.radius[i] > p.centre[high][axis] + p.radius[high])
      high = i;
  }
  if (low == p.size() || span <= kMaxSpanRadii * r_min) return;
  auto at = [&p](std::size_t i) {
    std::ostringstream s;
    s << "(" << p.centre[i].x() << ", " << p.centre[i].y() << ", " << p.centre[i].z() << ")";
    return s.str();
  };
  std::ostringstream m;
  m << "the packing spans " << span << " m along "
    << "xyz"[axis] << ", " << span / r_min << " times its smallest radius (" << r_min
    << " m): rays find hits to the digits a grazing "
    << "ray needs only across <= " << kMaxSpanRadii << " radii. Particles " << low << " at "
    << at(low) << " and " << high << " at " << at(high) << " bound it, particle " << smallest
    << " at " << at(smallest) << " has the smallest radius (counted from 0: a packing file's "
    << "rows in order, a stray row or a radius in other units?; or a generated packing's radius "
    << "far below its spacing, packing.radius_ratio)";
  throw InputError(m.str());
}

void validate(const OpticsSpec& spec, const Particles& particles) {
  check_span(particles);
  if (!(spec.cutoff >= 0.0 && spec.cutoff < 1.0))
    throw InputError("`optics.cutoff` = " + shown_number(spec.cutoff) + ": must be in [0, 1)");
  check_optics_tuning(spec);
  if (spec.max_bounces < 1)
    throw InputError("`optics.max_bounces` = " + std::to_string(spec.max_bounces) +
                     ": must be >= 1");
  for (std::size_t i = 0; i < particles.size(); ++i)
    if (particles.material[i] >= spec.materials.size())
      throw InputError("particle " + std::to_string(i) + " has material " +
                       std::to_string(particles.material[i]) + " but the optics spec defines " +
                       std::to_string(spec.materials.size()) + " material(s)");
  auto index_ok = [](std::complex<double> n) {
    return n.real() > 0.0 && n.real() <= kMaxIndex && n.imag() >= 0.0 && n.imag() <= kMaxIndex;
  };
  // Linear polarisation is followed only while it stays linear: real indices >= 1.
  auto keeps_linear = [](std::complex<double> n) { return n.imag() == 0.0 && n.real() >= 1.0; };
  const double psi = spec.polarisation.psi;
  if (spec.polarisation.linear && !(psi >= 0.0 && psi <= std::numbers::pi))
    throw InputError("`optics.polarisation` = " + std::to_string(psi * 180.0 / std::numbers::pi) +
                     " degrees: the field's angle in the beam disk must be in [0, 180]");
  for (const auto& m : spec.materials) {
    if (!index_ok(m.n_solid) || !index_ok(m.n_liquid) ||
        !(m.mu_hat >= kMinMu && m.mu_hat <= kMaxMu))
      throw InputError(optics_text(m) +
                       ": the indices must be > 0 and <= 1e6, the k >= 0 and <= 1e6 (k < 0 "
                       "would be a gain medium), mu_hat in [1e-100, 1e100]");
    if (spec.polarisation.linear && !(keeps_linear(m.n_solid) && keeps_linear(m.n_liquid)))
      throw InputError(
          "`optics.polarisation` with `optics.k_solid`/`k_liquid` > 0 or an index "
          "below 1: the reflected light is elliptical there, which is not followed; "
          "use optics.polarisation = \"unpolarised\"");
  }
}

// A hit as every search must report one (MODEL.md section 3): ahead of the ray's origin, on the
// surface of a sphere in the scene other than the one the ray just left, entered from outside.
// BEAMPACK_CHECKS builds only (geometry/check.h).
[[maybe_unused]] void check_hit(const RayState& s, const Particles& p, const EmbreeScene& scene,
                                std::uint32_t r) {
  const std::uint32_t i = s.next_particle[r];
  const double t = s.t_next[r];
  BEAMPACK_DCHECK(std::isfinite(t) && t >= 0.0, "ray %u: hit at t = %g m on particle %u", r, t, i);
  BEAMPACK_DCHECK(i < p.size() && i != s.last_particle[r] && !scene.removed(i),
                  "ray %u: hit particle %u of %zu, the one it just left (%u) or a removed one", r,
                  i, p.size(), s.last_particle[r]);
  const Vec3 point = s.origin[r] + t * s.direction[r];
  const double off = std::abs((point - p.centre[i]).norm() - p.radius[i]);
  BEAMPACK_DCHECK(off <= 1e-6 * p.radius[i] + 1e-12 * point.norm(),
                  "ray %u: hit point %g m off the surface of particle %u (R = %g m)", r, off, i,
                  p.radius[i]);
  const double d_dot_n = s.direction[r].dot(s.normal[r]);
  BEAMPACK_DCHECK(d_dot_n <= 1e-6 * s.normal[r].norm(),
                  "ray %u: hit particle %u from inside (d.n = %g, |n| = %g)", r, i, d_dot_n,
                  s.normal[r].norm());
}

// Unpolarised Fresnel reflectance (2.25) with the particle's current index (solid or liquid).
double particle_reflectance(const MaterialOptics& m, Phase phase, double cos_i) {
  const std::complex<double> n = phase == Phase::solid ? m.n_solid : m.n_liquid;
  return n.imag() == 0.0 ? reflectance(cos_i, n.real(), m.mu_hat) : reflectance(cos_i, n, m.mu_hat);
}

}  // namespace

void check_optics_tuning(const OpticsSpec& spec) {
  if (!(spec.grid_cell_factor > 0.0) || !std::isfinite(spec.grid_cell_factor))
    throw InputError("OpticsSpec::grid_cell_factor = " + shown_number(spec.grid_cell_factor) +
                     ": must be > 0 and finite");
  if (spec.chunk_rays < 1 || spec.chunk_rays > kMaxChunkRays)
    throw InputError("OpticsSpec::chunk_rays = " + std::to_string(spec.chunk_rays) +
                     ": must be in [1, " + std::to_string(kMaxChunkRays) + "]");
  if (spec.spheres_per_primitive < 1 || spec.spheres_per_primitive > kMaxSpheresPerPrimitive)
    throw InputError(
        "OpticsSpec::spheres_per_primitive = " + std::to_string(spec.spheres_per_primitive) +
        ": must be in [1, " + std::to_string(kMaxSpheresPerPrimitive) + "]");
}

double box_exit_distance(const Box& box, const Vec3& o, const Vec3& d) {
  double t_exit = std::numeric_limits<double>::infinity();
  for (int a = 0; a < 3; ++a) {
    if (d[a] > 0.0) t_exit = std::min(t_exit, (box.upper[a] - o[a]) / d[a]);
    else if (d[a] < 0.0) t_exit = std::min(t_exit, (box.lower[a] - o[a]) / d[a]);
  }
  return std::isfinite(t_exit) ? std::max(t_exit, 0.0) : 0.0;
}

// What happened to a ray: energy into a particle, out of the box, or below the cutoff.
constexpr std::uint32_t kEscapedBin = kNoParticle, kCutoffBin = kNoParticle - 1;
struct Event {
  std::uint32_t ray;
  std::uint32_t bin;  // particle id, kEscapedBin or kCutoffBin
  double energy;
};

// Per chunk: events sorted by ray (stable: each ray's own order), merged in chunk order, so the
// sums never depend on threads, on packets, or on the order rays were stepped in.
struct Tracer::Chunk {
  std::vector<Event> events;
  std::vector<Event> sorted;  // scratch of sort_events_by_ray
  // Scratch lists of ray ids (waves), kept with the chunk so no pulse allocates them.
  std::vector<std::uint32_t> active, next, walkers;
  std::vector<std::pair<std::uint32_t, RaySegment>> segments;  // when recording, by ray
  std::uint64_t primary = 0, bounced = 0, hits = 0;
  std::size_t ended = 0;
  double flight = 0.0;  // the most path a ray of the chunk travelled before it ended
  // The undo record (Tracer::keep_undo): each ray the advance changed, as it was before.
  std::size_t first = 0;  // the chunk's first ray
  std::bitset<kMaxChunkRays> remembered;
  std::vector<std::uint32_t> changed;
  RayState before;

  // Empty, keeping the storage: chunks are reused from one advance to the next.
  void clear(std::size_t first_ray, bool polarised) {
    events.clear();
    segments.clear();
    primary = bounced = hits = 0;
    ended = 0;
    flight = 0.0;
    first = first_ray;
    remembered.reset();
    changed.clear();
    before.polarised = polarised;
    before.for_each_array([](auto& v) { v.clear(); });
  }
};

// Ray r as it was before this advance changed it, kept once per advance when undo is on.
void Tracer::keep_before(std::uint32_t r, Chunk& c) const {
  if (c.remembered[r - c.first]) return;
  c.remembered[r - c.first] = true;
  c.changed.push_back(r);
  RayState::for_each_member(
      state_.polarised, [&](auto member) { (c.before.*member).push_back((state_.*member)[r]); });
}

Tracer::Tracer(const Particles& particles, OpticsSpec spec)
    : particles_(particles), spec_(std::move(spec)) {
  check_particles(particles);
  validate(spec_, particles);
  particle_count_ = particles.size();
  box_ = particles.bounds();
  state_.polarised = spec_.polarisation.linear;
}

// Built whole or not at all: a build that throws (an Embree device refusing its configuration)
// leaves the tracer as it was, and the next call tries again.
void Tracer::build_scene() {
  if (scene_) return;
  check_particle_count("the ray scene's build");
  auto scene = std::make_unique<EmbreeScene>(particles_, spec_.scene_update, 4096, 0.1,
                                             spec_.spheres_per_primitive, spec_.embree_config);
  // The grid serves bounced rays only: with optics.max_bounces = 1 every ray ends at its first hit.
  std::unique_ptr<SphereGrid> grid;
  if (spec_.bounce_search == BounceSearch::grid && spec_.max_bounces > 1)
    grid = std::make_unique<SphereGrid>(particles_, spec_.grid_cell_factor);
  // Both were built without the particles no longer alive; the others removed since come now.
  std::vector<std::uint32_t> removed = removed_unbuilt_;
  std::erase_if(removed, [&](std::uint32_t p) { return !particles_.alive[p]; });
  scene->remove(removed);
  if (grid) grid->remove(removed);
  scene_ = std::move(scene), grid_ = std::move(grid);
  removed_unbuilt_.clear();
}

std::size_t Tracer::scene_rebuilds() const {
  return scene_ ? scene_->rebuilds() : 0;
}

std::size_t Tracer::failed_scene_rebuilds() const {
  return scene_ ? scene_->failed_rebuilds() : 0;
}

std::string Tracer::last_failed_scene_rebuild() const {
  return scene_ ? scene_->last_failed_rebuild() : std::string();
}

void Tracer::finish_scene_rebuild() {
  if (scene_) scene_->finish_rebuild();
}

void Tracer::prepare_scene() {
  build_scene();
  scene_->poll_rebuild();  // a background rebuild taken or started (no query runs now)
}

void Tracer::check_particle_count(const char* when) const {
  if (particles_.size() != particle_count_)
    throw InputError(std::string(when) + ": the particles were " + std::to_string(particle_count_) +
                     " when the tracer took them and are " + std::to_string(particles_.size()) +
                     " now: a tracer's particles keep their count");
}

Tracer::~Tracer() = default;

// A beam made by hand (library callers; make_beam checks its own): a direction that is not a unit
// vector let every ray escape, a NaN energy made the ledger NaN.
void Tracer::check_launch(const Beam& beam, std::span<const double> energies) const {
  const double norm = beam.direction.norm();
  if (!(std::abs(norm - 1.0) <= 1e-9))
    throw InputError("launch: the beam's direction has |d| = " + shown_number(norm) +
                     ": must be a unit vector");
  for (std::size_t k = 0; k < energies.size(); ++k)
    if (!(energies[k] >= 0.0) || !std::isfinite(energies[k]))
      throw InputError("launch: ray " + std::to_string(k) + "'s energy " +
                       shown_number(energies[k]) + " J: must be >= 0 and finite");
  check_beam_points(beam);
  check_particle_count("launch");
}

// Where rays start: a NaN or far-off origin reached Embree as an invalid float ray, and Embree
// aborted the process. A ray is handed to Embree from where it enters the packing's box, computed
// in double, so a distant start keeps its precision (1e-9 m spheres lit from 1000 m are hit
// exactly): within 1e6 m (the largest sample.size) or 1e9 packing sizes, whichever is larger.
void Tracer::check_beam_points(const Beam& beam) const {
  const double size = box_.empty() ? 0.0 : (box_.upper - box_.lower).norm();
  const double reach = std::max(1e6, 1e9 * size);
  const Vec3 middle = box_.empty() ? Vec3::Zero() : Vec3(0.5 * (box_.lower + box_.upper));
  const auto within = [&, reach2 = reach * reach](const Vec3& point) {
    return (point - middle).squaredNorm() <= reach2;  // false for NaN and infinity too
  };
  const auto refuse = [&](const Vec3& point, const std::string& what) {
    throw InputError("launch: " + what + " (" + shown_number(point.x()) + ", " +
                     shown_number(point.y()) + ", " + shown_number(point.z()) +
                     ") m: must be finite and within " + shown_number(reach) +
                     " m of the packing (1e6 m, or 1e9 times its size)");
  };
  if (!within(beam.centre)) refuse(beam.centre, "the beam's centre");
  // Every launch passes over every ray here, serially: one pass without a branch or a square root
  // (a sqrt per ray took 0.27 ms of a 7 ms pulse of 10^5 rays), a second only to name the first
  // ray that fails.
  bool all_within = true;
  for (const Vec3& origin : beam.origin) all_within &= within(origin);
  if (all_within) return;
  for (std::size_t k = 0; k < beam.size(); ++k)
    if (!within(beam.origin[k])) refuse(beam.origin[k], "ray " + std::to_string(k) + "'s origin");
}

void Tracer::launch(const Beam& beam, double pulse_duration) {
  launch(beam, beam.ray_energies(pulse_duration));
}

void Tracer::launch(const Beam& beam, std::span<const double> energies) {
  if (energies.size() != beam.size())
    throw InputError("launch: " + std::to_string(energies.size()) + " energies for " +
                     std::to_string(beam.size()) + " rays");
  check_launch(beam, energies);
  prepare_scene();
  compact_if_sparse();
  undo_.held = false;
  const bool moved_live_rays = rebase_clock();  // each pulse starts at 0 on the path clock
  // Appended in the beam's order (already tiled); every array grown once, then filled in
  // parallel (each ray on its own) with the rays and their first hits.
  RayState& s = state_;
  const Launch l{beam, energies, start_plane(beam), beam_field(beam.direction), s.live.size()};
  const std::size_t count = beam.size(), blocks = (count + kBatchRays - 1) / kBatchRays;
  s.for_each_array([&](auto& v) { v.resize(l.first + count); });
  reset_first_hits_for(beam.direction, l.upstream, count);
  // The new chunks' next events while their rays are in cache, when no chunk straddles two
  // blocks (or the launch's first ray); otherwise afterwards.
  const std::size_t chunk = spec_.chunk_rays;
  const bool chunks_in_blocks = l.first % chunk == 0 && kBatchRays % chunk == 0;
  next_event_.resize((l.first + count + chunk - 1) / chunk);
  // The injected energy, summed in ray order beside the blocks (into a local: the ledger shares a
  // cache line with the array headers the blocks read).
  double injected = s.ledger.injected, injected_low = s.ledger.injected_low;
  tbb::task_group summing;
  summing.run([&] {
    const IeeeFloatMode ieee;
    double value = injected, low = injected_low;  // in registers, stored once
    for (double e : energies) add_compensated(value, low, e);
    injected = value, injected_low = low;
  });
  std::vector<std::size_t> traced(blocks);
  try {
    tbb::parallel_for(tbb::blocked_range<std::size_t>(0, blocks, 1),
                      [&](const tbb::blocked_range<std::size_t>& range) {
      const IeeeFloatMode ieee;  // the queries' double tests, on whatever thread
      for (std::size_t b = range.begin(); b != range.end(); ++b) {
        const std::size_t end = std::min(count, (b + 1) * kBatchRays);
        traced[b] = start_rays(l, b * kBatchRays, end);
        if (chunks_in_blocks)
          for (std::size_t j = (l.first + b * kBatchRays) / chunk; j * chunk < l.first + end; ++j)
            update_next_event(j);
      }
    });
  } catch (...) {  // (an Embree error, memory): the tracer as it was before the new rays
    summing.wait();
    s.for_each_array([&](auto& v) { v.resize(l.first); });
    refresh_next_events(0);
    throw;
  }
  summing.wait();
  s.ledger.injected = injected, s.ledger.injected_low = injected_low;
  const std::size_t queries = std::accumulate(traced.begin(), traced.end(), std::size_t{0});
  s.primary_segments += queries;
  s.reused_primaries += count - queries;
  s.live_count += count;
  if (!chunks_in_blocks) refresh_next_events(moved_live_rays ? 0 : l.first / chunk);
  else if (moved_live_rays) refresh_next_events(0, l.first / chunk);
}

// Start plane: upstream of every particle (spheres stick out of the cube by up to R), so the
// first surface a ray meets is a true outside hit (MODEL.md section 2). Its distance along the
// beam from the beam's centre.
double Tracer::start_plane(const Beam& beam) const {
  if (box_.empty()) return 0.0;
  double upstream = 0.0;
  for (int corner = 0; corner < 8; ++corner) {
    const Vec3 p((corner & 1) ? box_.upper.x() : box_.lower.x(),
                 (corner & 2) ? box_.upper.y() : box_.lower.y(),
                 (corner & 4) ? box_.upper.z() : box_.lower.z());
    upstream = std::min(upstream, (p - beam.centre).dot(beam.direction));
  }
  return upstream - 1e-6 * (box_.upper - box_.lower).norm();
}

// A polarised beam's field, at psi from the axis u towards v of polarisation_axes (zero when
// unpolarised).
Vec3 Tracer::beam_field(const Vec3& direction) const {
  if (!state_.polarised) return Vec3::Zero();
  Vec3 u, v;
  polarisation_axes(direction, u, v);
  return std::cos(spec_.polarisation.psi) * u + std::sin(spec_.polarisation.psi) * v;
}

// The kept first hits are this beam's (its direction, start plane and ray count): those of
// another beam are dropped, there is nothing to reuse.
void Tracer::reset_first_hits_for(const Vec3& direction, double upstream, std::size_t count) {
  FirstHits& f = first_hits_;
  if (!spec_.reuse_primaries ||
      (f.t.size() == count && f.direction == direction && f.upstream == upstream))
    return;
  f.direction = direction, f.upstream = upstream;
  f.origin.assign(count, Vec3::Constant(std::numeric_limits<double>::quiet_NaN()));
  f.normal.assign(count, Vec3::Zero());
  f.t.assign(count, 0.0);
  f.particle.assign(count, kNoParticle);
}

// Beam rays [begin, end) of launch l, as rays l.first + k: on the start plane with their energies
// (and the beam's field), and their first hits. Returns how many were traced (the others reused).
std::size_t Tracer::start_rays(const Launch& l, std::size_t begin, std::size_t end) {
  const Vec3& d = l.beam.direction;
  for (std::size_t k = begin; k < end; ++k) {
    start_ray(l.first + k, l.beam.origin[k] + l.upstream * d, d, l.energies[k]);
    if (state_.polarised) state_.field[l.first + k] = l.field;
  }
  return find_first_hits(l.beam, l.first, begin, end);
}

// The path clock back to 0, and the live rays' segment clocks with it: each keeps its path to its
// next event, to the round-off of that path (not of the clock). Without this, pulses overlapping
// without end would grow the clock, and every event comparison would lose eps x clock. True when
// live rays were moved (their chunks' next events are then stale).
bool Tracer::rebase_clock() {
  RayState& s = state_;
  const double shift = s.clock;
  s.clock = 0.0;
  if (shift == 0.0 || s.live_count == 0) return false;
  for (std::size_t r = 0; r < s.live.size(); ++r)
    if (s.live[r]) s.start_clock[r] -= shift;
  return true;
}

// Ray r at its launch: on the start plane, no bounce yet, not traced.
void Tracer::start_ray(std::size_t r, const Vec3& origin, const Vec3& direction, double energy) {
  RayState& s = state_;
  s.origin[r] = origin;
  s.direction[r] = direction;
  s.normal[r] = Vec3::Zero();
  s.energy[r] = s.initial_energy[r] = energy;
  s.start_clock[r] = s.clock;
  s.t_next[r] = -1.0;
  s.last_particle[r] = s.next_particle[r] = kNoParticle;
  s.bounces[r] = 0;
  s.live[r] = 1;
}

// The first hits of the launched rays [first + begin, first + end) (ray first + k is the beam's
// ray k): reused from the beam's last launch where they can be, the others traced in coherent
// packets (or one by one without packets). Returns how many were traced.
std::size_t Tracer::find_first_hits(const Beam& beam, std::size_t first, std::size_t begin,
                                    std::size_t end) {
  std::array<std::uint32_t, kBatchRays> ids;
  std::size_t m = 0;
  for (std::size_t k = begin; k < end; ++k) {
    const auto r = static_cast<std::uint32_t>(first + k);
    if (!reuse_first_hit(beam, k, r)) ids[m++] = r;
  }
  if (spec_.packets) {
    trace_ids(ids.data(), m, true);
  } else {
    for (std::size_t j = 0; j < m; ++j) trace_segment(ids[j]);
  }
  if (spec_.reuse_primaries)
    for (std::size_t j = 0; j < m; ++j) keep_first_hit(beam, ids[j] - first, ids[j]);
  return m;
}

// Beam ray k, launched as ray r, takes the first hit it had when it was last traced: the same
// point on the beam's disk (the launch checked the direction and the start plane), and the
// sphere it met not removed since (particles only disappear, so the nearest of the remaining
// ones is still that one). False: r must be traced.
bool Tracer::reuse_first_hit(const Beam& beam, std::size_t k, std::uint32_t r) {
  if (!spec_.reuse_primaries) return false;
  const FirstHits& f = first_hits_;
  RayState& s = state_;
  const std::uint32_t p = f.particle[k];
  if (f.origin[k] != beam.origin[k] || (p != kNoParticle && scene_->removed(p))) return false;
  s.t_next[r] = f.t[k];
  s.next_particle[r] = p;
  s.normal[r] = f.normal[k];
  return true;
}

// Ray r, just traced from its launch point, is beam ray k's first hit from now on.
void Tracer::keep_first_hit(const Beam& beam, std::size_t k, std::uint32_t r) {
  FirstHits& f = first_hits_;
  const RayState& s = state_;
  f.origin[k] = beam.origin[k], f.normal[k] = s.normal[r];
  f.t[k] = s.t_next[r];
  f.particle[k] = s.next_particle[r];
}

double Tracer::energy_in_flight() const {
  double sum = 0.0;
  for (std::size_t r = 0; r < state_.live.size(); ++r)
    if (state_.live[r]) sum += state_.energy[r];
  return sum;
}

void Tracer::compact_if_sparse() {
  if (state_.live_count * 2 < state_.live.size()) compact();
}

void Tracer::compact() {
  undo_.held = false;
  RayState& s = state_;
  std::vector<std::size_t> keep;
  if (s.live_count > 0)  // else every ray ended: nothing to look at
    for (std::size_t r = 0; r < s.live.size(); ++r)
      if (s.live[r]) keep.push_back(r);
  s.for_each_array([&](auto& v) {
    for (std::size_t w = 0; w < keep.size(); ++w) v[w] = v[keep[w]];
    v.resize(keep.size());
  });
  refresh_next_events(0);
}

// A state from elsewhere (a library caller's): checked as a checkpoint's rays are, against this
// tracer's particles (one from a larger packing indexed past them).
void Tracer::restore(const RayState& state) {
  check_restorable(state, "restore");
  undo_.held = false;
  state_ = state;
  refresh_next_events(0);
}

void Tracer::check_restorable(const RayState& state, const char* when) const {
  check_particle_count(when);
  if (state.polarised != state_.polarised)
    throw InputError(std::string(when) + ": the state's rays are " +
                     (state.polarised ? "polarised" : "unpolarised") +
                     " and this tracer's are not");
  state.check_lengths(when);
  state.check_values(particles_.size(), when);
  state.check_live_count(when);
}

// The earliest event of the live rays [begin, end) on the path clock: -infinity when one is still
// to be traced (or its event is not a number: the chunk runs, and the NaN reaches the checks
// instead of leaving a live ray that never runs), +infinity when none is live.
double Tracer::next_event_of_chunk(std::size_t begin, std::size_t end) const {
  const RayState& s = state_;
  double first = kInf;
  for (std::size_t r = begin; r < end; ++r) {
    if (!s.live[r]) continue;
    const double event = s.start_clock[r] + s.t_next[r];
    first = std::min(first, s.t_next[r] < 0.0 || std::isnan(event) ? -kInf : event);
  }
  return first;
}

// Chunk k's next event, from its rays.
void Tracer::update_next_event(std::size_t k) {
  const std::size_t begin = k * spec_.chunk_rays;
  next_event_[k] =
      next_event_of_chunk(begin, std::min(state_.live.size(), begin + spec_.chunk_rays));
}

// The chunks from first_chunk on take their next events from their rays; the list follows the
// ray arrays as they grow and shrink.
void Tracer::refresh_next_events(std::size_t first_chunk, std::size_t end_chunk) {
  const std::size_t chunks = (state_.live.size() + spec_.chunk_rays - 1) / spec_.chunk_rays;
  next_event_.resize(chunks);
  for (std::size_t k = first_chunk; k < std::min(chunks, end_chunk); ++k) update_next_event(k);
}

namespace {
RayQuery query_of(RayState& s) {
  return {s.origin.data(), s.direction.data(),     s.last_particle.data(),
          s.t_next.data(), s.next_particle.data(), s.normal.data()};
}
}  // namespace

// Before a search for ray r's next event: none known yet, the search keeps the nearest hit.
void Tracer::open_query(std::uint32_t r) {
  state_.t_next[r] = std::numeric_limits<double>::infinity();
  state_.next_particle[r] = kNoParticle;
}

// After it: no hit means the next event is leaving the box (MODEL.md 3a). True when it hit.
bool Tracer::close_query(std::uint32_t r) {
  RayState& s = state_;
  if (s.next_particle[r] != kNoParticle) {
    if constexpr (BEAMPACK_CHECKS_ON) check_hit(s, particles_, *scene_, r);
    return true;
  }
  s.t_next[r] = box_exit_distance(box_, s.origin[r], s.direction[r]);
  return false;
}

// Nearest outside hit of one ray's segment through Embree (BounceSearch::embree), or the distance
// to where it leaves the box.
void Tracer::trace_segment(std::uint32_t r) {
  open_query(r);
  scene_->intersect1(query_of(state_), r);
  close_query(r);
}

// Traces the listed rays in packets of 16 consecutive ones (coherent: a tile of the beam).
void Tracer::trace_ids(const std::uint32_t* ids, std::size_t count, bool coherent) {
  const RayQuery q = query_of(state_);
  for (std::size_t k = 0; k < count; ++k) open_query(ids[k]);
  for (std::size_t k = 0; k < count; k += kPacket)
    scene_->intersect16(q, ids + k, static_cast<int>(std::min<std::size_t>(kPacket, count - k)),
                        coherent);
  for (std::size_t k = 0; k < count; ++k)
    if (close_query(ids[k]))  // the phase is read when the hit is processed
      __builtin_prefetch(&particles_.phase[state_.next_particle[ids[k]]]);
}

// One wave of queries: the next nearest hit of every listed ray. Bounced rays walk the grid,
// interleaved; primaries (here only when the sphere their launch found was removed on the way)
// go to Embree one by one.
void Tracer::trace_wave(const std::vector<std::uint32_t>& rays, Chunk& c) {
  if (spec_.bounce_search == BounceSearch::packets) {
    trace_ids(rays.data(), rays.size(), false);
    return;
  }
  RayState& s = state_;
  const RayQuery q = query_of(s);
  std::vector<std::uint32_t>& walkers = c.walkers;
  walkers.clear();
  for (std::uint32_t r : rays) {
    open_query(r);
    if (s.bounces[r] > 0) walkers.push_back(r);
    else scene_->intersect1(q, r);
  }
  if (grid_) grid_->intersect_many(q, walkers);
  else  // no grid (max_bounces = 1): no bounced ray should get here; Embree answers if one does
    for (std::uint32_t r : walkers) scene_->intersect1(q, r);
  for (std::uint32_t r : rays) close_query(r);
}

// Moves ray r through its events up to the path clock's end_clock. A hit deposits (1 - R) E in
// the particle (3.3) and reflects the ray specularly, d' = d - 2 (d.n) n, carrying R E on.
// Returns true when the ray needs its next segment traced, false when it is done for this call.
bool Tracer::step_ray(std::uint32_t r, double end_clock, Chunk& c) {
  RayState& s = state_;
  for (;;) {
    if (s.t_next[r] < 0.0) {
      remember(r, c);
      return true;
    }
    const double event = s.start_clock[r] + s.t_next[r];
    if (event > end_clock) return false;  // in free flight at the end: the ray resumes here
    remember(r, c);
    const std::uint32_t p = s.next_particle[r];
    // Removed since this segment was traced: traced again from its origin. Particles only
    // disappear, so the new event lies beyond this one, and nothing was missed on the way.
    if (p != kNoParticle && scene_->removed(p)) {
      s.t_next[r] = -1.0;
      return true;
    }
    if (record_segments_)
      c.segments.push_back(
          {r, {s.origin[r], s.origin[r] + s.t_next[r] * s.direction[r], s.energy[r]}});
    if (p == kNoParticle) {  // left the box: escaped (MODEL.md 3a)
      c.events.push_back({r, kEscapedBin, s.energy[r]});
      end_ray(r, event, c);
      return false;
    }
    const Vec3 point = s.origin[r] + s.t_next[r] * s.direction[r];
    const Vec3 normal = near_unit(s.normal[r]);  // entry_normal from the scene
    const double cos_i = -s.direction[r].dot(normal);
    // One material (the usual case): no per-particle lookup, one cache miss fewer per hit.
    const MaterialOptics& m =
        spec_.materials.size() == 1 ? spec_.materials[0] : spec_.materials[particles_.material[p]];
    const double R = s.polarised ? reflect_field(r, normal, m, particles_.phase[p])
                                 : particle_reflectance(m, particles_.phase[p], cos_i);
    const double carried = R * s.energy[r];
    BEAMPACK_DCHECK(R >= 0.0 && R <= 1.0 && std::isfinite(carried),
                    "ray %u at particle %u: reflectance %.17g (cos_i %.17g), energy %.17g J", r, p,
                    R, cos_i, s.energy[r]);
    c.events.push_back({r, p, s.energy[r] - carried});  // absorbed + carried == E exactly
    ++c.hits;
    s.energy[r] = carried;
    s.bounces[r] += 1;
    // A ray left with nothing ends whatever the cutoff: with optics.cutoff = 0 it would bounce on
    // carrying 0 J, and its flight would lengthen a "pulse" step (and delay an "auto" pulse).
    if (carried == 0.0 || carried < spec_.cutoff * s.initial_energy[r] ||
        s.bounces[r] >= spec_.max_bounces) {
      c.events.push_back({r, kCutoffBin, carried});  // MODEL.md 3b, 3c
      end_ray(r, event, c);  // its direction and origin are not updated (fewer stores per ray)
      return false;
    }
    s.direction[r] = near_unit(reflect(s.direction[r], normal));
    s.origin[r] = point;
    s.last_particle[r] = p;
    s.start_clock[r] = event;
    s.t_next[r] = -1.0;
  }
}

// Ray r ends at path clock `at`: its flight in this advance counts towards the step's length.
void Tracer::end_ray(std::uint32_t r, double at, Chunk& c) {
  state_.live[r] = 0;
  ++c.ended;
  c.flight = std::max(c.flight, at - state_.clock);
}

// Ray r's reflectance at a hit with its own field, which turns into the reflected ray's field.
double Tracer::reflect_field(std::uint32_t r, const Vec3& normal, const MaterialOptics& m,
                             Phase phase) {
  RayState& s = state_;
  const double n_hat = (phase == Phase::solid ? m.n_solid : m.n_liquid).real();
  const PolarisedReflection out =
      reflect_polarised(s.direction[r], normal, s.field[r], n_hat, m.mu_hat);
  s.field[r] = out.field;
  return out.reflectance;
}

void Tracer::count_segment(std::uint32_t r, Chunk& c) const {
  (state_.bounces[r] == 0 ? c.primary : c.bounced) += 1;
}

void Tracer::run_chunk(Chunk& c, std::size_t begin, std::size_t end, double end_clock) {
  trace_chunk(c, begin, end, end_clock);
  update_next_event(begin / spec_.chunk_rays);
}

// Advances rays [begin, end) to the path clock's end_clock (their launch traced their first
// segments): the next segments one ray at a time (BounceSearch::embree) or in waves (packets,
// grid).
void Tracer::trace_chunk(Chunk& c, std::size_t begin, std::size_t end, double end_clock) {
  const RayState& s = state_;
  if (spec_.bounce_search == BounceSearch::embree) {
    for (std::size_t r = begin; r < end; ++r) {
      if (!s.live[r]) continue;
      const auto ray = static_cast<std::uint32_t>(r);
      while (step_ray(ray, end_clock, c)) {
        count_segment(ray, c);
        trace_segment(ray);
      }
    }
    return;
  }
  trace_in_waves(c, begin, end, end_clock);
}

// Every live ray steps to its next query, then the wave's queries run together (interleaved grid
// walks, or incoherent packets), until no ray needs another. A ray's events stay in its own
// order but interleave with other rays'; they are put back in ray order at the end.
void Tracer::trace_in_waves(Chunk& c, std::size_t begin, std::size_t end, double end_clock) {
  std::vector<std::uint32_t>& active = c.active;
  std::vector<std::uint32_t>& next = c.next;
  active.clear();
  for (std::size_t r = begin; r < end; ++r)
    if (state_.live[r]) active.push_back(static_cast<std::uint32_t>(r));
  int waves = 0;
  for (; !active.empty(); ++waves) {
    next.clear();
    for (std::uint32_t r : active)
      if (step_ray(r, end_clock, c)) next.push_back(r), count_segment(r, c);
    trace_wave(next, c);
    active.swap(next);
  }
  if (waves > 1) sort_events_by_ray(c, begin, end);  // one wave: already in ray order
}

// Stable counting sort of the chunk's events by ray: O(events), no comparisons.
void Tracer::sort_events_by_ray(Chunk& c, std::size_t begin, std::size_t end) {
  std::array<std::uint32_t, kMaxChunkRays + 1> start{};
  for (const Event& e : c.events) ++start[e.ray - begin + 1];
  for (std::size_t k = 0; k + 1 < end - begin + 1; ++k) start[k + 1] += start[k];
  c.sorted.resize(c.events.size());
  for (const Event& e : c.events) c.sorted[start[e.ray - begin]++] = e;
  c.events.swap(c.sorted);
}

void RayState::write(StateWriter& out) const {
  out.value(polarised);  // first: it says whether the field array follows
  for_each_array([&](const auto& v) { out.vector(v); });
  out.value(ledger), out.value(primary_segments), out.value(bounced_segments), out.value(hits);
  out.value(reused_primaries), out.value(live_count), out.value(clock);
}

void RayState::read(StateReader& in) {
  polarised = in.value<bool>();
  for_each_array([&](auto& v) { in.vector(v); });
  ledger = in.value<OpticsLedger>(), primary_segments = in.value<std::uint64_t>();
  bounced_segments = in.value<std::uint64_t>(), hits = in.value<std::uint64_t>();
  reused_primaries = in.value<std::uint64_t>(), live_count = in.value<std::size_t>(),
  clock = in.value<double>();
  for_each_array([&](const auto& v) {
    if (v.size() != origin.size()) throw InputError("checkpoint: ray arrays of unequal length");
  });
  check_live_count("checkpoint");
}

void RayState::check_lengths(const std::string& source) const {
  for_each_array([&](const auto& v) {
    if (v.size() != live.size())
      throw InputError(source + ": a per-ray array holds " + std::to_string(v.size()) +
                       " entries for " + std::to_string(live.size()) + " rays");
  });
}

// The tracer trusts live_count (a compaction with none live drops every ray without looking).
void RayState::check_live_count(const std::string& source) const {
  const auto live_rays = static_cast<std::size_t>(
      std::count_if(live.begin(), live.end(), [](auto l) { return l != 0; }));
  if (live_rays != live_count)
    throw InputError(source + ": live_count = " + std::to_string(live_count) + " but " +
                     std::to_string(live_rays) + " rays are live");
}

void RayState::check_values(std::size_t particles, const std::string& source) const {
  auto bad = [&](const std::string& what, std::size_t r) {
    throw InputError(source + ": ray " + std::to_string(r) + " has " + what);
  };
  auto finite = [](const Vec3& v) { return v.allFinite(); };
  for (std::size_t r = 0; r < live.size(); ++r) {
    for (const std::uint32_t p : {last_particle[r], next_particle[r]})
      if (p != kNoParticle && p >= particles)
        bad("particle " + std::to_string(p) + ", beyond the " + std::to_string(particles) +
                " particles",
            r);
    if (!(energy[r] >= 0 && energy[r] <= initial_energy[r] && std::isfinite(initial_energy[r])))
      bad("energy " + shown_number(energy[r]) + " J of " + shown_number(initial_energy[r]) + " J",
          r);
    if (!(finite(origin[r]) && finite(direction[r]) && std::isfinite(start_clock[r]) &&
          !std::isnan(t_next[r])))
      bad("a position, direction or clock that is not a finite number", r);
    if (live[r] > 1 || bounces[r] < 0) bad("a live flag or bounce count out of range", r);
  }
  const OpticsLedger& l = ledger;
  for (const double v : {l.injected, l.absorbed, l.escaped, l.cutoff, clock})
    if (!(std::isfinite(v) && v >= 0))
      throw InputError(source + ": a ledger entry or the clock is " + shown_number(v));
  // A low part is what its sum rounded away: within half an ulp of it, either sign.
  for (const auto& [value, low] : {std::pair{l.injected, l.injected_low},
                                   {l.absorbed, l.absorbed_low},
                                   {l.escaped, l.escaped_low},
                                   {l.cutoff, l.cutoff_low}})
    if (!(std::abs(low) <= 1e-15 * value))
      throw InputError(source + ": a ledger entry's low part is " + shown_number(low) +
                       " against its " + shown_number(value) + " J");
}

void Tracer::write_first_hits(StateWriter& out) const {
  const FirstHits& f = first_hits_;
  for (int a = 0; a < 3; ++a) out.value(f.direction[a]);
  out.value(f.upstream);
  out.vector(f.origin), out.vector(f.normal), out.vector(f.t), out.vector(f.particle);
}

Tracer::FirstHits Tracer::read_first_hits(StateReader& in) const {
  FirstHits f;
  for (int a = 0; a < 3; ++a) f.direction[a] = in.value<double>();
  f.upstream = in.value<double>();
  in.vector(f.origin), in.vector(f.normal), in.vector(f.t), in.vector(f.particle);
  const std::size_t n = f.origin.size();
  if (f.normal.size() != n || f.t.size() != n || f.particle.size() != n)
    throw InputError("checkpoint: first-hit arrays of unequal length");
  for (std::uint32_t p : f.particle)
    if (p != kNoParticle && p >= particles_.size())
      throw InputError("checkpoint: a first hit on particle " + std::to_string(p) + " of " +
                       std::to_string(particles_.size()));
  for (const double t : f.t)
    if (!(t >= 0)) throw InputError("checkpoint: a first hit at distance " + shown_number(t));
  // A kept hit's point and normal are used as they are (NaN origins: deposits of NaN).
  for (std::size_t k = 0; k < n; ++k)
    if (f.particle[k] != kNoParticle && !(f.origin[k].allFinite() && f.normal[k].allFinite()))
      throw InputError("checkpoint: first hit " + std::to_string(k) +
                       " has a point or normal that is not finite");
  return f;
}

// Adds a traced chunk to the deposits, the ledger and the counters: ray order inside the chunk,
// each ray's event order (the chunks come in chunk order).
void Tracer::add_chunk(Chunk& c, std::vector<double>& deposits,
                       std::vector<std::uint32_t>* deposited) {
  Totals& t = totals_;
  t.flight = std::max(t.flight, c.flight);
  if (record_segments_) {  // ray order inside the chunk, whatever order the rays were stepped in
    std::stable_sort(c.segments.begin(), c.segments.end(),
                     [](const auto& a, const auto& b) { return a.first < b.first; });
    for (const auto& seg : c.segments) segments_.push_back(seg.second);
  }
  for (const Event& e : c.events) {
    BEAMPACK_DCHECK(std::isfinite(e.energy) && e.energy >= 0.0,
                    "ray %u: an event of %g J into bin %u", e.ray, e.energy, e.bin);
    OpticsLedger& l = t.ledger;
    if (e.bin == kEscapedBin) {
      add_compensated(l.escaped, l.escaped_low, e.energy);
    } else if (e.bin == kCutoffBin) {
      add_compensated(l.cutoff, l.cutoff_low, e.energy);
    } else {
      double& deposit = deposits[e.bin];
      if (deposited && deposit == 0 && e.energy != 0) deposited->push_back(e.bin);
      deposit += e.energy;
      add_compensated(l.absorbed, l.absorbed_low, e.energy);
    }
  }
  t.primary += c.primary;
  t.bounced += c.bounced;
  t.hits += c.hits;
  t.ended += c.ended;
}

// The chunks with an event before end_clock, into due_chunks_; returns how many others hold live
// rays in free flight throughout (each flies the whole budget).
std::size_t Tracer::select_due_chunks(double end_clock) {
  std::vector<std::uint32_t>& due = due_chunks_;
  due.clear();
  std::size_t idle = 0;
  for (std::size_t k = 0; k < next_event_.size(); ++k) {
    if (next_event_[k] <= end_clock && next_event_[k] < kInf)
      due.push_back(static_cast<std::uint32_t>(k));
    else idle += next_event_[k] < kInf;
  }
  return idle;
}

// What undo_advance restores: the tracer's counts before this advance (the rays' own states are
// kept by the chunks as they first change them).
void Tracer::open_undo_record() {
  if (!undo_.on) return;
  const RayState& s = state_;
  undo_ = {.on = true,
           .held = true,
           .ledger = s.ledger,
           .primary = s.primary_segments,
           .bounced = s.bounced_segments,
           .hits = s.hits,
           .live_count = s.live_count,
           .clock = s.clock,
           .last_advance_path = last_advance_path_,
           .last_chunks_live = last_chunks_live_,
           .last_chunks_run = last_chunks_run_,
           .segments = segments_.size()};
}

// Chunks per pipeline item: kBatchRays rays at least, and about kItemsPerThread items per thread
// when there are more chunks (an item costs the pipeline about a microsecond: with 256 rays per
// item, a 10^5-ray pulse spent a fifth of its stepping on them).
std::size_t Tracer::chunks_per_batch() const {
  const std::size_t threads =
      std::min(static_cast<std::size_t>(tbb::this_task_arena::max_concurrency()),
               tbb::global_control::active_value(tbb::global_control::max_allowed_parallelism));
  return std::max({std::size_t{1}, kBatchRays / spec_.chunk_rays,
                   due_chunks_.size() / (kItemsPerThread * threads)});
}

// Runs the due chunks in parallel and sums them one by one in chunk order as they finish, so the
// (serial, deterministic) reduction overlaps the tracing of later chunks.
void Tracer::run_due_chunks(double end_clock, std::vector<double>& deposits,
                            std::vector<std::uint32_t>* deposited) {
  const std::vector<std::uint32_t>& due = due_chunks_;
  if (chunks_.size() < due.size()) chunks_.resize(due.size());
  const std::size_t n = state_.live.size(), per_batch = chunks_per_batch();
  const std::size_t batches = (due.size() + per_batch - 1) / per_batch;
  std::size_t next = 0;
  tbb::parallel_pipeline(
      kBatchesInFlight,
      tbb::make_filter<void, std::size_t>(tbb::filter_mode::serial_in_order,
                                          [&](tbb::flow_control& control) -> std::size_t {
                                            if (next == batches) control.stop();
                                            return next++;
                                          }) &
          tbb::make_filter<std::size_t, std::size_t>(
              tbb::filter_mode::parallel,
              [this, n, end_clock, per_batch](std::size_t b) {  // by value: no shared stack line
    const IeeeFloatMode ieee;  // whatever thread TBB runs this batch on (engine/float_mode.h)
    for (std::size_t j = b * per_batch; j < std::min(due_chunks_.size(), (b + 1) * per_batch);
         ++j) {
      Chunk& chunk = chunks_[j];
      const std::size_t begin = due_chunks_[j] * spec_.chunk_rays;
      chunk.clear(begin, state_.polarised);
      run_chunk(chunk, begin, std::min(n, begin + spec_.chunk_rays), end_clock);
    }
    return b;
              }) &
      tbb::make_filter<std::size_t, void>(tbb::filter_mode::serial_in_order, [&](std::size_t b) {
        const IeeeFloatMode ieee;  // the sums must not flush denormals on some threads only
        for (std::size_t j = b * per_batch; j < std::min(due.size(), (b + 1) * per_batch); ++j)
          add_chunk(chunks_[j], deposits, deposited);
      }));
}

// Traces every live ray on by path_budget (of path length): the chunks with an event before the
// advance's end are run (run_due_chunks), the others are in free flight throughout, and nothing of
// theirs changes. Returns the rays still live.
std::size_t Tracer::advance(double path_budget, std::vector<double>& deposits,
                            std::vector<std::uint32_t>* deposited) {
  if (!(path_budget >= 0.0))
    throw InputError("advance: path budget " + shown_number(path_budget) + " must be >= 0");
  check_particle_count("advance");  // fewer particles: the rays' hits would index past them
  if (deposits.size() < particles_.size()) deposits.resize(particles_.size(), 0.0);
  if (has_live_rays()) prepare_scene();
  RayState& s = state_;
  const double end_clock = s.clock + path_budget;
  const std::size_t idle = select_due_chunks(end_clock);
  totals_ = Totals{};
  totals_.ledger = s.ledger;  // summed on in the same order as ever: bit-identical ledgers
  open_undo_record();
  last_chunks_live_ = due_chunks_.size() + idle;
  last_chunks_run_ = due_chunks_.size();
  run_due_chunks(end_clock, deposits, deposited);
  bool rays_fly_on = idle > 0;  // some ray is still in free flight at the advance's end
  for (std::uint32_t k : due_chunks_) rays_fly_on |= next_event_[k] < kInf;
  s.ledger = totals_.ledger;
  s.primary_segments += totals_.primary;
  s.bounced_segments += totals_.bounced;
  s.hits += totals_.hits;
  s.live_count -= totals_.ended;
  last_advance_path_ = rays_fly_on ? std::max(totals_.flight, path_budget) : totals_.flight;
  s.clock += std::isfinite(path_budget) ? path_budget : last_advance_path_;
  return s.live_count;
}

void Tracer::keep_undo(bool on) {
  undo_.on = on;
  undo_.held = false;
}

void Tracer::undo_advance() {
  if (!undo_.held)  // as ThermalModel::undo_step: a silent no-op left the advance's rays done
    throw RunError(
        "undo_advance: no advance to undo (keep_undo(true) before it, and no launch, removal, "
        "compaction or restore since; once per advance)");
  RayState& s = state_;
  for (std::size_t j = 0; j < due_chunks_.size(); ++j) {
    const Chunk& c = chunks_[j];
    for (std::size_t w = 0; w < c.changed.size(); ++w)
      RayState::for_each_member(
          s.polarised, [&](auto member) { (s.*member)[c.changed[w]] = (c.before.*member)[w]; });
    update_next_event(due_chunks_[j]);
  }
  s.ledger = undo_.ledger;
  s.primary_segments = undo_.primary, s.bounced_segments = undo_.bounced, s.hits = undo_.hits;
  s.live_count = undo_.live_count;
  s.clock = undo_.clock;
  last_advance_path_ = undo_.last_advance_path;
  last_chunks_live_ = undo_.last_chunks_live, last_chunks_run_ = undo_.last_chunks_run;
  segments_.resize(std::min(segments_.size(), undo_.segments));  // the undone advance's segments
  undo_.held = false;
}

// Rays already on their way to a removed particle find out when they get there (step_ray): the
// removal itself does not look at the rays.
void Tracer::remove_particles(std::span<const std::uint32_t> ids) {
  undo_.held = false;
  if (!scene_) {
    check_removal_ids(ids, particles_.size());
    removed_unbuilt_.insert(removed_unbuilt_.end(), ids.begin(), ids.end());
    return;
  }
  // The grid first (it checks the ids before changing anything, as the scene does): were the
  // scene's removal to throw after masking, a grid still offering a masked particle would send a
  // ray back to it for ever (step_ray retraces on a removed hit).
  if (grid_) grid_->remove(ids);
  scene_->remove(ids);
}

}  // namespace beampack
