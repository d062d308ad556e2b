#include "engine/sphere_grid.h"

#include <algorithm>
#include <array>
#include <cmath>
#include <limits>
#include <string>

#include "geometry/error.h"
#include "geometry/ray_sphere.h"

namespace beampack {
namespace {
constexpr std::uint32_t kNone = std::numeric_limits<std::uint32_t>::max();
// Spheres are registered in every cell their box grown by this fraction of a cell touches, so
// the walk's stopping rule (best hit before the current cell's exit) survives round-off in the
// cell boundaries (~1e-16 relative, far below this).
constexpr double kRegisterPad = 1e-6;
}  // namespace

SphereGrid::SphereGrid(const Particles& particles, double cell_factor) {
  const std::size_t n = particles.size();
  if (!(cell_factor > 0.0)) throw InputError("SphereGrid: cell factor must be > 0");
  for (std::size_t i = 0; i < n; ++i) box_.grow(particles.centre[i], particles.radius[i]);
  if (box_.empty()) box_.grow(Vec3::Zero(), 1.0);
  // Pad beyond rounding: a ray just outside a sphere's bounding plane (by an ulp or a denormal)
  // can still meet the sphere in the double test, where |perp|^2 rounds to R^2. Such a ray must
  // be inside the grid's box, or the walk would skip a hit Embree and the brute force find.
  const double pad = 1e-9 * ((box_.upper - box_.lower).norm() + box_.lower.cwiseAbs().maxCoeff() +
                             box_.upper.cwiseAbs().maxCoeff()) +
                     1e-300;
  box_.lower -= Vec3::Constant(pad);
  box_.upper += Vec3::Constant(pad);
  const Vec3 extent = (box_.upper - box_.lower).cwiseMax(Vec3::Constant(1e-300));
  double r_max = 0.0;
  for (double r : particles.radius) r_max = std::max(r_max, r);
  h_ = std::max(cell_factor * r_max, extent.maxCoeff() * 1e-6);
  // Memory bound: no more than ~4 cells per sphere (and at least one cell).
  const double max_cells = 4.0 * static_cast<double>(std::max<std::size_t>(n, 1)) + 64.0;
  auto padded = [&](double e) { return 4.0 * std::ceil(std::ceil(e / h_) / 4.0); };
  while (padded(extent.x()) * padded(extent.y()) * padded(extent.z()) > max_cells) h_ *= 1.25;
  inv_h_ = 1.0 / h_;
  for (int a = 0; a < 3; ++a) {
    dims_[a] = std::max(1L, static_cast<long>(std::ceil(extent[a] * inv_h_)));
    blocks_[a] = (dims_[a] + 3) / 4;
  }

  // Every entry a copy of its sphere in double: the exact test needs no second, random load.
  spheres_.resize(n);
  for (std::size_t p = 0; p < n; ++p)
    spheres_[p] = {particles.centre[p],
                   particles.alive[p] ? particles.radius[p] : -particles.radius[p]};
  // CSR fill in two passes: count, then place.
  const std::size_t cell_count =
      static_cast<std::size_t>(blocks_[0] * blocks_[1] * blocks_[2] * 64);
  start_.assign(cell_count + 1, 0);
  for (std::size_t p = 0; p < n; ++p)
    for_cells(spheres_[p], [&](std::size_t c) { ++start_[c + 1]; });
  for (std::size_t c = 0; c < cell_count; ++c) start_[c + 1] += start_[c];
  entries_.resize(start_[cell_count]);
  std::vector<std::uint32_t> fill(start_.begin(), start_.end() - 1);
  for (std::size_t p = 0; p < n; ++p)
    for_cells(spheres_[p], [&](std::size_t c) {
      entries_[fill[c]++] = {spheres_[p].centre, spheres_[p].radius, static_cast<std::uint32_t>(p)};
    });
}

long SphereGrid::cell_of(double x, int axis) const {
  return std::clamp(static_cast<long>(std::floor((x - box_.lower[axis]) * inv_h_)), 0L,
                    dims_[axis] - 1);
}

// Calls visit(cell) for every cell that the sphere's box, grown by kRegisterPad cells, touches.
template <class Visit>
void SphereGrid::for_cells(const Sphere& sphere, Visit&& visit) const {
  const double r = std::abs(sphere.radius) + kRegisterPad * h_;
  long lo[3], hi[3];
  for (int a = 0; a < 3; ++a)
    lo[a] = cell_of(sphere.centre[a] - r, a), hi[a] = cell_of(sphere.centre[a] + r, a);
  for (long z = lo[2]; z <= hi[2]; ++z)
    for (long y = lo[1]; y <= hi[1]; ++y)
      for (long x = lo[0]; x <= hi[0]; ++x) visit(static_cast<std::size_t>(cell_index(x, y, z)));
}

// Negates the radius of the particle and of every entry that copies it.
void SphereGrid::remove(std::span<const std::uint32_t> ids) {
  check_removal_ids(ids, spheres_.size());
  for (std::uint32_t p : ids) {
    Sphere& sphere = spheres_[p];
    sphere.radius = -std::abs(sphere.radius);
    for_cells(sphere, [&](std::size_t c) {
      for (std::uint32_t k = start_[c]; k < start_[c + 1]; ++k)
        if (entries_[k].particle == p) entries_[k].radius = sphere.radius;
    });
  }
}

// One ray's walk. A single 3D-DDA runs two cells ahead of the tests and queues the cells it
// enters with the distance at which the ray leaves each; entering a cell prefetches its start_
// row, and a cell's entries are prefetched one visit before it is tested (the walk is bound by
// memory latency). Self-contained, so that intersect_many can keep several in flight.
struct SphereGrid::Walk {
  Vec3 o, d;
  long step[3];
  double t_delta[3];
  double t1;  // end of the ray's interval clipped to the box
  double best;
  std::uint32_t who, best_entry, skip, ray;  // skip: the particle the ray has just left
  long cell[3];  // the DDA: the last cell queued, and where the ray crosses its walls
  double t_max[3];
  int exit_axis;   // the wall through which the ray leaves that cell
  bool more;       // the DDA can still queue a cell
  long queue[3];   // queue[0]: the cell to test now
  double exit[3];  // where the ray leaves each queued cell
  int queued;
};

namespace {
// The axis whose cell wall the ray crosses first (ties as in t0 < t1 ? (t0 < t2 ? 0 : 2) :
// (t1 < t2 ? 1 : 2)), without branches: which wall comes first is a coin toss the branch
// predictor loses at every step.
int nearest_exit_axis(const double* t_max) {
  const int c01 = t_max[0] < t_max[1], c02 = t_max[0] < t_max[2], c12 = t_max[1] < t_max[2];
  return c01 * (2 - 2 * c02) + (1 - c01) * (2 - c12);
}
}  // namespace

// Clips ray id to the grid's box and sets up its walk; false when nothing in the box can be hit.
bool SphereGrid::start_walk(const RayQuery& q, std::uint32_t id, Walk& w) const {
  const Vec3& o = q.origin[id];
  const Vec3& d = q.direction[id];
  // Reciprocal once, products after: the walk starts at every bounce, and the DDA's distances
  // need no exact rounding (cells are registered with a pad far above it).
  const Vec3 inv_d(1.0 / d.x(), 1.0 / d.y(), 1.0 / d.z());
  double t0 = 0.0, t1 = q.t_hit[id];
  for (int a = 0; a < 3; ++a) {
    if (d[a] != 0.0) {
      const double ta = (box_.lower[a] - o[a]) * inv_d[a], tb = (box_.upper[a] - o[a]) * inv_d[a];
      t0 = std::max(t0, std::min(ta, tb));
      t1 = std::min(t1, std::max(ta, tb));
    } else if (o[a] < box_.lower[a] || o[a] > box_.upper[a]) {
      return false;
    }
  }
  if (!(t0 <= t1)) return false;
  w.o = o, w.d = d, w.t1 = t1, w.ray = id;
  for (int a = 0; a < 3; ++a) {
    const double x = o[a] + t0 * d[a];
    const auto from_lower = static_cast<long>(std::floor((x - box_.lower[a]) * inv_h_));
    w.cell[a] = std::clamp(from_lower, 0L, dims_[a] - 1);
    w.step[a] = d[a] > 0.0 ? 1 : -1;
    if (d[a] != 0.0) {
      const double boundary = box_.lower[a] + static_cast<double>(w.cell[a] + (d[a] > 0.0)) * h_;
      w.t_max[a] = (boundary - o[a]) * inv_d[a];
      w.t_delta[a] = h_ * std::abs(inv_d[a]);
    } else {
      w.t_max[a] = w.t_delta[a] = std::numeric_limits<double>::infinity();
    }
  }
  w.skip = q.skip[id];
  w.best = q.t_hit[id];
  w.who = q.particle[id];
  w.best_entry = kNone;
  w.more = true;
  w.queued = 0;
  enqueue(w, cell_index(w.cell[0], w.cell[1], w.cell[2]));
  while (w.queued < 3 && step_dda(w)) {
  }
  return true;
}

// Queues cell c, the DDA's current cell, with where the ray leaves it; prefetches its start_ row.
void SphereGrid::enqueue(Walk& w, long c) const {
  __builtin_prefetch(&start_[static_cast<std::size_t>(c)]);
  w.exit_axis = nearest_exit_axis(w.t_max);
  w.queue[w.queued] = c;
  w.exit[w.queued] = w.t_max[w.exit_axis];
  ++w.queued;
}

// Moves the DDA into the next cell along the ray and queues it; false once the ray's interval
// ends in the last cell queued, or the next cell is outside the grid.
bool SphereGrid::step_dda(Walk& w) const {
  if (!w.more) return false;
  const int a = w.exit_axis;
  w.cell[a] += w.step[a];
  if (w.t_max[a] > w.t1 || w.cell[a] < 0 || w.cell[a] >= dims_[a]) return w.more = false;
  w.t_max[a] += w.t_delta[a];
  enqueue(w, cell_index(w.cell[0], w.cell[1], w.cell[2]));
  return true;
}

// Tests the spheres registered in cell c; keeps the nearest hit, ties to the lower particle id.
// Most entries are misses: the line passes them by, or they lie behind (sphere_approach, without
// the entry's square root and division), and removed ones have r < 0.
void SphereGrid::test_cell(Walk& w, std::size_t c) const {
  for (std::uint32_t k = start_[c]; k < start_[c + 1]; ++k) {
    const Entry& e = entries_[k];
    if (!(e.radius > 0.0)) continue;
    const SphereApproach approach = sphere_approach(w.o, w.d, e.centre, e.radius);
    if (!approach.ahead_and_met()) continue;
    const double t = ray_sphere_entry(approach);
    if (!(t < kNoHit)) continue;
    const std::uint32_t p = e.particle;
    if (p == w.skip) continue;
    if (t < w.best || (t == w.best && p < w.who)) w.best = t, w.who = p, w.best_entry = k;
  }
}

// Prefetches the first entries of a cell whose start_ row was prefetched a visit earlier (a
// cell holds about four: three cache lines).
void SphereGrid::prefetch_entries(long cell) const {
  const auto* first =
      reinterpret_cast<const char*>(&entries_[start_[static_cast<std::size_t>(cell)]]);
  for (int line = 0; line < 3; ++line) __builtin_prefetch(first + 64 * line);
}

// Tests the walk's current cell and moves on to the next; false when the walk is over.
bool SphereGrid::visit_cell(Walk& w) const {
  if (w.queued > 1) prefetch_entries(w.queue[1]);
  test_cell(w, static_cast<std::size_t>(w.queue[0]));
  // Any hit nearer than this cell's exit has its entry point in a cell already walked.
  if (w.best <= w.exit[0] || w.exit[0] > w.t1 || w.queued == 1) return false;
  w.queue[0] = w.queue[1], w.exit[0] = w.exit[1];
  w.queue[1] = w.queue[2], w.exit[1] = w.exit[2];
  --w.queued;
  step_dda(w);
  return true;
}

// Writes a finished walk's hit to the query (untouched when the walk found none).
void SphereGrid::record_hit(const RayQuery& q, const Walk& w) const {
  if (w.best_entry == kNone) return;
  q.t_hit[w.ray] = w.best;
  q.particle[w.ray] = w.who;
  const Entry& sp = entries_[w.best_entry];
  if (q.normal) q.normal[w.ray] = entry_normal(w.o, w.d, w.best, sp.centre, sp.radius);
}

void SphereGrid::intersect1(const RayQuery& q, std::uint32_t id) const {
  Walk w;
  if (!start_walk(q, id, w)) return;
  while (visit_cell(w)) {
  }
  record_hit(q, w);
}

// Walks in flight in intersect_many: enough that a round of the other walks' cells covers a
// memory latency. Of 4, 8 and 16, 8 measured fastest at 10^6 spheres (trace/grid_batch in
// benchmarks/bench_trace.cpp, medians 700, 650, 770 ns per bounced ray on a shared 2-core
// machine, before the entries carried doubles); 6, 8, 12 and 16 measure alike since.
constexpr int kWalksInFlight = 8;

void SphereGrid::intersect_many(const RayQuery& q, std::span<const std::uint32_t> ids) const {
  std::array<Walk, kWalksInFlight> ring;
  // A walk just started spends its first round prefetching its first cell's entries (start_walk
  // prefetched the cell's start_ row): tested at once, it would stall on two misses in a row.
  std::array<bool, kWalksInFlight> fresh;
  std::size_t taken = 0;
  auto start_next = [&](int i) {  // the next listed ray that enters the box, if any is left
    while (taken < ids.size())
      if (start_walk(q, ids[taken++], ring[i])) return fresh[i] = true;
    return false;
  };
  int live = 0;
  while (live < kWalksInFlight && start_next(live)) ++live;
  while (live > 0) {
    for (int i = 0; i < live;) {
      if (fresh[i]) {
        fresh[i] = false;
        prefetch_entries(ring[i].queue[0]);
      } else if (!visit_cell(ring[i])) {
        record_hit(q, ring[i]);
        if (!start_next(i)) {
          --live;
          ring[i] = ring[live], fresh[i] = fresh[live];
          continue;  // slot i now holds a walk not yet visited this round
        }
      }
      ++i;
    }
  }
}

}  // namespace beampack
