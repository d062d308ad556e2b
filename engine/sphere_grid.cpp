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
                             box_.upper.cwiseAbs().maxCoeff()) + 1e-300;
  box_.lower -= Vec3::Constant(pad);
  box_.upper += Vec3::Constant(pad);
  const Vec3 extent = (box_.upper - box_.lower).cwiseMax(Vec3::Constant(1e-300));
  double r_max = 0.0;
  for (double r : particles.radius) r_max = std::max(r_max, r);
  h_ = std::max(cell_factor * r_max, extent.maxCoeff() * 1e-6);
  // Memory bound: no more than ~4 cells per sphere (and at least one cell).
  const double max_cells = 4.0 * static_cast<double>(std::max<std::size_t>(n, 1)) + 64.0;
  auto padded = [&](double e) { return 4.0 * std::ceil(std::ceil(e / h_) / 4.0); };
  while (padded(extent.x()) * padded(extent.y()) * padded(extent.z()) > max_cells)
    h_ *= 1.25;
  inv_h_ = 1.0 / h_;
  for (int a = 0; a < 3; ++a) {
    dims_[a] = std::max(1L, static_cast<long>(std::ceil(extent[a] * inv_h_)));
    blocks_[a] = (dims_[a] + 3) / 4;
  }

  auto cell_of = [&](double x, int a) {
    return std::clamp(static_cast<long>(std::floor((x - box_.lower[a]) * inv_h_)), 0L, dims_[a] - 1);
  };
  // Spheres in the order of their centre's cell: the spheres of a cell sit together in memory.
  std::vector<std::pair<long, std::uint32_t>> order(n);
  for (std::size_t i = 0; i < n; ++i) {
    const Vec3& c = particles.centre[i];
    order[i] = {cell_index(cell_of(c.x(), 0), cell_of(c.y(), 1), cell_of(c.z(), 2)),
                static_cast<std::uint32_t>(i)};
  }
  std::sort(order.begin(), order.end());
  spheres_.resize(n);
  particle_.resize(n);
  slot_.resize(n);
  for (std::size_t s = 0; s < n; ++s) {
    const std::uint32_t p = order[s].second;
    particle_[s] = p;
    slot_[p] = static_cast<std::uint32_t>(s);
    spheres_[s] = {particles.centre[p], particles.alive[p] ? particles.radius[p] : -particles.radius[p]};
  }
  // CSR fill in two passes: count, then place.
  const std::size_t cell_count = static_cast<std::size_t>(blocks_[0] * blocks_[1] * blocks_[2] * 64);
  start_.assign(cell_count + 1, 0);
  auto for_cells = [&](std::size_t s, auto&& visit) {
    const Sphere& sp = spheres_[s];
    const double r = std::abs(sp.radius) + kRegisterPad * h_;
    long lo[3], hi[3];
    for (int a = 0; a < 3; ++a) lo[a] = cell_of(sp.centre[a] - r, a), hi[a] = cell_of(sp.centre[a] + r, a);
    for (long z = lo[2]; z <= hi[2]; ++z)
      for (long y = lo[1]; y <= hi[1]; ++y)
        for (long x = lo[0]; x <= hi[0]; ++x) visit(static_cast<std::size_t>(cell_index(x, y, z)));
  };
  for (std::size_t s = 0; s < n; ++s) for_cells(s, [&](std::size_t c) { ++start_[c + 1]; });
  for (std::size_t c = 0; c < cell_count; ++c) start_[c + 1] += start_[c];
  entry_sphere_.resize(start_[cell_count]);
  entry_slot_.resize(start_[cell_count]);
  std::vector<std::uint32_t> fill(start_.begin(), start_.end() - 1);
  for (std::size_t s = 0; s < n; ++s)
    for_cells(s, [&](std::size_t c) {
      const Sphere& sp = spheres_[s];
      entry_sphere_[fill[c]] = {static_cast<float>(sp.centre.x()), static_cast<float>(sp.centre.y()),
                                static_cast<float>(sp.centre.z()), static_cast<float>(std::abs(sp.radius))};
      entry_slot_[fill[c]++] = static_cast<std::uint32_t>(s);
    });
  prefilter_pad_ = static_cast<float>(1e-6 * ((box_.upper - box_.lower).norm() +
                                              box_.lower.cwiseAbs().maxCoeff() +
                                              box_.upper.cwiseAbs().maxCoeff()));
}

void SphereGrid::remove(std::span<const std::uint32_t> ids) {
  for (std::uint32_t p : ids) {
    if (p >= slot_.size())
      throw InputError("remove_particles: particle id " + std::to_string(p) + " >= count " +
                       std::to_string(slot_.size()));
    Sphere& s = spheres_[slot_[p]];
    s.radius = -std::abs(s.radius);
  }
}

// The 3D-DDA state of one ray, its best hit so far, and a copy of the DDA running two cells
// ahead that prefetches (the walk is bound by memory latency): each visit prefetches the entries
// of the next cell, whose start_ row was prefetched a visit earlier. Self-contained, so that
// intersect_many can keep several in flight.
struct SphereGrid::Walk {
  Vec3 o, d;
  float fo[3], fd[3];  // for the float prefilter
  long cell[3], step[3];
  double t_max[3], t_delta[3];
  double t1;  // end of the ray's interval clipped to the box
  double best;
  std::uint32_t who, best_slot, skip, ray;
  long ahead[3];
  double ahead_t[3];
  bool ahead_ok;
  long next1, next2;  // the next two cells (-1: the walk ends first)
};

namespace {
int nearest_exit_axis(const double* t_max) {
  return t_max[0] < t_max[1] ? (t_max[0] < t_max[2] ? 0 : 2) : (t_max[1] < t_max[2] ? 1 : 2);
}
}  // namespace

// Clips ray id to the grid's box and sets up its walk; false when nothing in the box can be hit.
bool SphereGrid::start_walk(const RayQuery& q, std::uint32_t id, Walk& w) const {
  const Vec3& o = q.origin[id];
  const Vec3& d = q.direction[id];
  double t0 = 0.0, t1 = q.t_hit[id];
  for (int a = 0; a < 3; ++a) {
    if (d[a] != 0.0) {
      const double ta = (box_.lower[a] - o[a]) / d[a], tb = (box_.upper[a] - o[a]) / d[a];
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
      w.t_max[a] = (boundary - o[a]) / d[a];
      w.t_delta[a] = h_ / std::abs(d[a]);
    } else {
      w.t_max[a] = w.t_delta[a] = std::numeric_limits<double>::infinity();
    }
    w.fo[a] = static_cast<float>(o[a]);
    w.fd[a] = static_cast<float>(d[a]);
    w.ahead[a] = w.cell[a];
    w.ahead_t[a] = w.t_max[a];
  }
  w.skip = q.skip[id] < slot_.size() ? slot_[q.skip[id]] : kNone;
  w.best = q.t_hit[id];
  w.who = q.particle[id];
  w.best_slot = kNone;
  w.ahead_ok = true;
  __builtin_prefetch(&start_[static_cast<std::size_t>(current_cell(w))]);
  w.next1 = step_ahead(w);
  w.next2 = step_ahead(w);
  return true;
}

long SphereGrid::current_cell(const Walk& w) const {
  return cell_index(w.cell[0], w.cell[1], w.cell[2]);
}

// Advances the lookahead copy of the DDA by one cell and prefetches that cell's start_ row.
long SphereGrid::step_ahead(Walk& w) const {
  if (!w.ahead_ok) return -1;
  const int a = nearest_exit_axis(w.ahead_t);
  w.ahead[a] += w.step[a];
  if (w.ahead_t[a] > w.t1 || w.ahead[a] < 0 || w.ahead[a] >= dims_[a]) {
    w.ahead_ok = false;
    return -1;
  }
  w.ahead_t[a] += w.t_delta[a];
  const long c = cell_index(w.ahead[0], w.ahead[1], w.ahead[2]);
  __builtin_prefetch(&start_[static_cast<std::size_t>(c)]);
  return c;
}

// Tests the spheres registered in cell c; keeps the nearest hit, ties to the lower particle id.
void SphereGrid::test_cell(Walk& w, std::size_t c) const {
  for (std::uint32_t k = start_[c]; k < start_[c + 1]; ++k) {
    // Float prefilter: passes within r + pad of the centre, centre not behind by more.
    const FloatSphere& f = entry_sphere_[k];
    const float fx = w.fo[0] - f.x, fy = w.fo[1] - f.y, fz = w.fo[2] - f.z;
    const float b = -(fx * w.fd[0] + fy * w.fd[1] + fz * w.fd[2]);
    const float px = fx + b * w.fd[0], py = fy + b * w.fd[1], pz = fz + b * w.fd[2];
    const float reach = f.r + prefilter_pad_;
    if (px * px + py * py + pz * pz > reach * reach || b < -reach) continue;
    const std::uint32_t s = entry_slot_[k];
    const Sphere& sp = spheres_[s];
    if (s == w.skip || !(sp.radius > 0.0)) continue;
    const double t = ray_sphere_entry(w.o, w.d, sp.centre, sp.radius);
    if (!(t < kNoHit)) continue;
    const std::uint32_t p = particle_[s];
    if (t < w.best || (t == w.best && p < w.who)) w.best = t, w.who = p, w.best_slot = s;
  }
}

// Prefetches the first entries of a cell whose start_ row was prefetched a visit earlier.
void SphereGrid::prefetch_entries(long cell) const {
  const std::uint32_t first = start_[static_cast<std::size_t>(cell)];
  __builtin_prefetch(&entry_sphere_[first]);
  __builtin_prefetch(&entry_slot_[first]);
}

// Tests the walk's current cell and steps to the next one; false when the walk is over.
bool SphereGrid::visit_cell(Walk& w) const {
  const auto c = static_cast<std::size_t>(current_cell(w));
  if (w.next1 >= 0) prefetch_entries(w.next1);
  test_cell(w, c);
  // Any hit nearer than this cell's exit has its entry point in a cell already walked.
  const int axis = nearest_exit_axis(w.t_max);
  if (w.best <= w.t_max[axis] || w.t_max[axis] > w.t1) return false;
  w.cell[axis] += w.step[axis];
  if (w.cell[axis] < 0 || w.cell[axis] >= dims_[axis]) return false;
  w.t_max[axis] += w.t_delta[axis];
  w.next1 = w.next2;
  w.next2 = step_ahead(w);
  return true;
}

// Writes a finished walk's hit to the query (untouched when the walk found none).
void SphereGrid::record_hit(const RayQuery& q, const Walk& w) const {
  if (w.best_slot == kNone) return;
  q.t_hit[w.ray] = w.best;
  q.particle[w.ray] = w.who;
  const Sphere& sp = spheres_[w.best_slot];
  if (q.normal) q.normal[w.ray] = (w.o + w.best * w.d - sp.centre) / sp.radius;
}

bool SphereGrid::intersect1(const RayQuery& q, std::uint32_t id, long max_cells) const {
  Walk w;
  if (!start_walk(q, id, w)) return true;
  for (long walked = 0;; ++walked) {
    if (walked == max_cells) return false;
    if (!visit_cell(w)) break;
  }
  record_hit(q, w);
  return true;
}

// Walks in flight in intersect_many: enough that a round of the other walks' cells covers a
// memory latency. Of 4, 8 and 16, 8 measured fastest at 10^6 spheres (trace/grid_batch in
// benchmarks/bench_trace.cpp, medians 700, 650, 770 ns per bounced ray on a shared 2-core
// machine); beyond that, more walks in flight did not help.
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
        prefetch_entries(current_cell(ring[i]));
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
