#pragma once
// Uniform grid of cubic cells over the live particles, stored as compressed rows (counting sort):
// the neighbour search of the contact graph and of the packings, linear in N.
#include <array>
#include <cstdint>
#include <vector>

#include "particles.h"

namespace beampack {

class CellGrid {
 public:
  // Cells of edge >= cell_size over the live particles' centres.
  CellGrid(const Particles& particles, double cell_size);
  // An empty grid over a box, filled one point at a time with insert() (packing generation).
  CellGrid(const Box& centre_box, double cell_size, std::size_t expected_points);

  // Calls visit(j) for every particle in the 27 cells around p.
  template <class Visit>
  void for_each_neighbour(const Vec3& p, Visit&& visit) const {
    const auto c = cell_of(p);
    for (long z = std::max<long>(c[2] - 1, 0); z <= std::min<long>(c[2] + 1, dims_[2] - 1); ++z)
      for (long y = std::max<long>(c[1] - 1, 0); y <= std::min<long>(c[1] + 1, dims_[1] - 1); ++y)
        for (long x = std::max<long>(c[0] - 1, 0); x <= std::min<long>(c[0] + 1, dims_[0] - 1); ++x)
          visit_cell(index(x, y, z), visit);
  }
  void insert(const Vec3& p, std::uint32_t id);

  // Static grid only: cells in memory order, each a contiguous run [begin, end) of slots whose
  // particle ids, centres and radii are stored in cell order (cache-friendly neighbour scans).
  std::size_t cell_count() const { return start_.empty() ? 0 : start_.size() - 1; }
  std::uint32_t begin(std::size_t cell) const { return start_[cell]; }
  std::uint32_t end(std::size_t cell) const { return start_[cell + 1]; }
  std::uint32_t id(std::uint32_t slot) const { return ids_[slot]; }
  const Vec3& centre(std::uint32_t slot) const { return centres_[slot]; }
  double radius(std::uint32_t slot) const { return radii_[slot]; }
  // Calls visit(cell) for the (up to 27) cells around cell `c`, `c` included.
  template <class Visit>
  void for_each_neighbour_cell(std::size_t c, Visit&& visit) const {
    const long x0 = long(c % dims_[0]), y0 = long((c / dims_[0]) % dims_[1]),
               z0 = long(c / (dims_[0] * dims_[1]));
    for (long z = std::max<long>(z0 - 1, 0); z <= std::min<long>(z0 + 1, dims_[2] - 1); ++z)
      for (long y = std::max<long>(y0 - 1, 0); y <= std::min<long>(y0 + 1, dims_[1] - 1); ++y)
        for (long x = std::max<long>(x0 - 1, 0); x <= std::min<long>(x0 + 1, dims_[0] - 1); ++x)
          visit(index(x, y, z));
  }

 private:
  template <class Visit>
  void visit_cell(std::size_t cell, Visit& visit) const {
    if (!dynamic_.empty()) {
      for (std::uint32_t id : dynamic_[cell]) visit(id);
      return;
    }
    for (std::uint32_t k = start_[cell]; k < start_[cell + 1]; ++k) visit(ids_[k]);
  }
  std::array<long, 3> cell_of(const Vec3& p) const;
  std::size_t index(long x, long y, long z) const {
    return static_cast<std::size_t>((z * dims_[1] + y) * dims_[0] + x);
  }
  void set_dims(const Box& box, double cell_size, std::size_t max_cells);

  Vec3 origin_;
  double inv_cell_ = 0.0;
  std::array<long, 3> dims_{1, 1, 1};
  std::vector<std::uint32_t> start_, ids_;  // static grid (CSR)
  std::vector<Vec3> centres_;               // static grid, in slot order
  std::vector<double> radii_;
  std::vector<std::vector<std::uint32_t>> dynamic_;  // insert-as-you-go grid
};

}  // namespace beampack
