#include "geometry/cell_grid.h"

#include <algorithm>
#include <cmath>

namespace beampack {

void CellGrid::set_dims(const Box& box, double cell_size, std::size_t max_cells) {
  origin_ = box.lower;
  const Vec3 extent = (box.upper - box.lower).cwiseMax(0.0);
  double h = std::max(cell_size, 1e-300);
  // Cap the cell count near the point count so that huge boxes with tiny spheres stay O(N) memory.
  for (;;) {
    // Clamped before the cast: a box 1e19 cells wide (spheres of 1e-17 m a kilometre apart) is
    // beyond a long, and the cast undefined; the loop widens the cells from there.
    for (int a = 0; a < 3; ++a)
      dims_[a] = std::max<long>(1, static_cast<long>(std::min(extent[a] / h, 1e15)));
    const double cells = double(dims_[0]) * double(dims_[1]) * double(dims_[2]);
    if (cells <= double(std::max<std::size_t>(max_cells, 1))) break;
    h *= 1.26;
  }
  // Cells h wide (the last one in each axis takes the remainder): a neighbour closer than h is
  // always in one of the 27 cells around a point.
  inv_cell_ = 1.0 / h;
}

std::array<long, 3> CellGrid::cell_of(const Vec3& p) const {
  std::array<long, 3> c{};
  for (int a = 0; a < 3; ++a) {
    const double s = std::floor((p[a] - origin_[a]) * inv_cell_);
    c[a] = std::clamp<long>(static_cast<long>(std::clamp(s, -1.0, 1e15)), 0, dims_[a] - 1);
  }
  return c;
}

CellGrid::CellGrid(const Particles& particles, double cell_size) {
  Box centres;
  for (std::size_t i = 0; i < particles.size(); ++i)
    if (particles.alive[i]) centres.grow(particles.centre[i], 0.0);
  if (centres.empty()) centres.grow(Vec3::Zero(), 0.0);
  set_dims(centres, cell_size, 2 * particles.size() + 8);
  const std::size_t cells = static_cast<std::size_t>(dims_[0] * dims_[1] * dims_[2]);
  start_.assign(cells + 1, 0);
  std::vector<std::uint32_t> cell_id(particles.size());
  for (std::size_t i = 0; i < particles.size(); ++i) {
    if (!particles.alive[i]) continue;
    const auto c = cell_of(particles.centre[i]);
    cell_id[i] = static_cast<std::uint32_t>(index(c[0], c[1], c[2]));
    ++start_[cell_id[i] + 1];
  }
  for (std::size_t k = 0; k < cells; ++k) start_[k + 1] += start_[k];
  ids_.resize(start_[cells]);
  centres_.resize(start_[cells]);
  radii_.resize(start_[cells]);
  std::vector<std::uint32_t> fill(start_.begin(), start_.end() - 1);
  for (std::size_t i = 0; i < particles.size(); ++i) {
    if (!particles.alive[i]) continue;
    const std::uint32_t slot = fill[cell_id[i]]++;
    ids_[slot] = static_cast<std::uint32_t>(i);
    centres_[slot] = particles.centre[i];
    radii_[slot] = particles.radius[i];
  }
}

CellGrid::CellGrid(const Box& centre_box, double cell_size, std::size_t expected_points) {
  set_dims(centre_box, cell_size, 2 * expected_points + 8);
  dynamic_.resize(static_cast<std::size_t>(dims_[0] * dims_[1] * dims_[2]));
}

void CellGrid::insert(const Vec3& p, std::uint32_t id) {
  const auto c = cell_of(p);
  dynamic_[index(c[0], c[1], c[2])].push_back(id);
}

}  // namespace beampack
