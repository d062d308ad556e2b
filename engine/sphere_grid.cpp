#include "engine/sphere_grid.h"

#include <algorithm>
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

bool SphereGrid::intersect1(const RayQuery& q, std::uint32_t id, long max_cells) const {
  const Vec3& o = q.origin[id];
  const Vec3& d = q.direction[id];
  // Clip the ray to the grid's box.
  double t0 = 0.0, t1 = q.t_hit[id];
  for (int a = 0; a < 3; ++a) {
    if (d[a] != 0.0) {
      const double ta = (box_.lower[a] - o[a]) / d[a], tb = (box_.upper[a] - o[a]) / d[a];
      t0 = std::max(t0, std::min(ta, tb));
      t1 = std::min(t1, std::max(ta, tb));
    } else if (o[a] < box_.lower[a] || o[a] > box_.upper[a]) {
      return true;
    }
  }
  if (!(t0 <= t1)) return true;
  long cell[3], step[3];
  double t_max[3], t_delta[3];
  for (int a = 0; a < 3; ++a) {
    const double x = o[a] + t0 * d[a];
    cell[a] = std::clamp(static_cast<long>(std::floor((x - box_.lower[a]) * inv_h_)), 0L, dims_[a] - 1);
    step[a] = d[a] > 0.0 ? 1 : -1;
    if (d[a] != 0.0) {
      const double boundary = box_.lower[a] + static_cast<double>(cell[a] + (d[a] > 0.0)) * h_;
      t_max[a] = (boundary - o[a]) / d[a];
      t_delta[a] = h_ / std::abs(d[a]);
    } else {
      t_max[a] = t_delta[a] = std::numeric_limits<double>::infinity();
    }
  }
  const std::uint32_t skip = q.skip[id] < slot_.size() ? slot_[q.skip[id]] : kNone;
  double best = q.t_hit[id];
  std::uint32_t who = q.particle[id], best_slot = kNone;
  const float ox = static_cast<float>(o.x()), oy = static_cast<float>(o.y()), oz = static_cast<float>(o.z());
  const float dx = static_cast<float>(d.x()), dy = static_cast<float>(d.y()), dz = static_cast<float>(d.z());
  // Lookahead: a copy of the walk runs two cells ahead and prefetches, so the next cells' rows
  // and entries arrive while this cell is tested (the walk is bound by memory latency).
  long ahead[3] = {cell[0], cell[1], cell[2]};
  double ahead_t[3] = {t_max[0], t_max[1], t_max[2]};
  bool ahead_ok = true;
  auto step_ahead = [&]() -> long {
    if (!ahead_ok) return -1;
    const int a = ahead_t[0] < ahead_t[1] ? (ahead_t[0] < ahead_t[2] ? 0 : 2) : (ahead_t[1] < ahead_t[2] ? 1 : 2);
    ahead[a] += step[a];
    if (ahead_t[a] > t1 || ahead[a] < 0 || ahead[a] >= dims_[a]) return ahead_ok = false, -1;
    ahead_t[a] += t_delta[a];
    const long c = cell_index(ahead[0], ahead[1], ahead[2]);
    __builtin_prefetch(&start_[static_cast<std::size_t>(c)]);
    return c;
  };
  long next1 = step_ahead(), next2 = step_ahead();
  for (long walked = 0;; ++walked) {
    if (walked == max_cells) return false;
    const auto c = static_cast<std::size_t>(cell_index(cell[0], cell[1], cell[2]));
    if (next1 >= 0) {
      const std::uint32_t first = start_[static_cast<std::size_t>(next1)];
      __builtin_prefetch(&entry_sphere_[first]);
      __builtin_prefetch(&entry_slot_[first]);
    }
    for (std::uint32_t k = start_[c]; k < start_[c + 1]; ++k) {
      // Float prefilter: passes within r + pad of the centre, centre not behind by more.
      const FloatSphere& f = entry_sphere_[k];
      const float fx = ox - f.x, fy = oy - f.y, fz = oz - f.z;
      const float b = -(fx * dx + fy * dy + fz * dz);
      const float px = fx + b * dx, py = fy + b * dy, pz = fz + b * dz;
      const float reach = f.r + prefilter_pad_;
      if (px * px + py * py + pz * pz > reach * reach || b < -reach) continue;
      const std::uint32_t s = entry_slot_[k];
      const Sphere& sp = spheres_[s];
      if (s == skip || !(sp.radius > 0.0)) continue;
      const double t = ray_sphere_entry(o, d, sp.centre, sp.radius);
      if (!(t < kNoHit)) continue;
      const std::uint32_t p = particle_[s];
      if (t < best || (t == best && p < who)) best = t, who = p, best_slot = s;
    }
    // Any hit nearer than this cell's exit has its entry point in a cell already walked.
    const int axis = t_max[0] < t_max[1] ? (t_max[0] < t_max[2] ? 0 : 2) : (t_max[1] < t_max[2] ? 1 : 2);
    if (best <= t_max[axis] || t_max[axis] > t1) break;
    cell[axis] += step[axis];
    if (cell[axis] < 0 || cell[axis] >= dims_[axis]) break;
    t_max[axis] += t_delta[axis];
    next1 = next2;
    next2 = step_ahead();
  }
  if (best_slot == kNone) return true;
  q.t_hit[id] = best;
  q.particle[id] = who;
  if (q.normal) q.normal[id] = (o + best * d - spheres_[best_slot].centre) / spheres_[best_slot].radius;
  return true;
}

}  // namespace beampack
