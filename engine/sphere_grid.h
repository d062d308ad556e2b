#pragma once
// Uniform grid over the spheres, walked cell by cell along a ray (Amanatides & Woo 3D-DDA).
// For bounced rays: they start on a sphere and travel a few radii (the mean free path of the
// paper's packing is ~ R / (pi L^3) ~ 9 R), so a walk through a handful of cells beats a BVH
// descent from the root (docs/bench/optics.md). Same answer as EmbreeScene, bit for bit: the
// nearest outside hit in double, the sphere just left skipped, ties to the lower particle id.
#include <cstdint>
#include <span>
#include <vector>

#include "../geometry/particles.h"
#include "ray_query.h"

namespace beampack {

class SphereGrid {
 public:
  // Cells of edge cell_factor * (largest radius), at most ~4 cells per sphere.
  explicit SphereGrid(const Particles& particles, double cell_factor = 3.0);

  void remove(std::span<const std::uint32_t> ids);
  // Nearest outside hit of ray ray_id before query.t_hit[ray_id] (same contract as EmbreeScene).
  void intersect1(const RayQuery& query, std::uint32_t ray_id) const;
  // Nearest outside hits of the listed rays (same contract as intersect1, same answer bit for
  // bit for each ray). The walks are interleaved cell by cell, a few rays in flight at once, so
  // one ray's cache misses overlap another's work.
  void intersect_many(const RayQuery& query, std::span<const std::uint32_t> ray_ids) const;

  std::size_t cells() const { return start_.empty() ? 0 : start_.size() - 1; }

 private:
  struct alignas(32) Sphere {
    Vec3 centre;
    double radius;  // negated once removed
  };
  // Cells stored in 4x4x4 blocks: a walk's next cell is usually in the same block (same pages
  // and nearby cache lines), unlike plain z-major order where a z step jumps a whole slab.
  long cell_index(long x, long y, long z) const {
    return (((z >> 2) * blocks_[1] + (y >> 2)) * blocks_[0] + (x >> 2)) * 64 +
           ((z & 3) * 16 + (y & 3) * 4 + (x & 3));
  }

  // One ray's walk: intersect1 runs one to its end, intersect_many several in turn, cell by cell
  // (sphere_grid.cpp).
  long cell_of(double x, int axis) const;
  template <class Visit>
  void for_cells(const Sphere& sphere, Visit&& visit) const;
  struct Walk;
  bool start_walk(const RayQuery& query, std::uint32_t ray_id, Walk& walk) const;
  void enqueue(Walk& walk, long cell) const;
  bool step_dda(Walk& walk) const;
  void prefetch_entries(long cell) const;
  void test_cell(Walk& walk, std::size_t cell) const;
  bool visit_cell(Walk& walk) const;
  void record_hit(const RayQuery& query, const Walk& walk) const;

  Box box_;
  double h_ = 1.0, inv_h_ = 1.0;
  long dims_[3] = {1, 1, 1};
  long blocks_[3] = {1, 1, 1};
  std::vector<Sphere> spheres_;  // by particle id (removal finds a sphere's cells from it)
  // CSR: cell -> entries, each a copy of a sphere registered in the cell with its particle id
  // (one record: a hit needs no second, random load).
  struct Entry {
    Vec3 centre;
    double radius;  // negated once removed
    std::uint32_t particle;
  };
  std::vector<std::uint32_t> start_;
  std::vector<Entry> entries_;
};

}  // namespace beampack
