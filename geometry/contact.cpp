#include "geometry/contact.h"

#include <tbb/parallel_for.h>
#include <tbb/parallel_sort.h>

#include <algorithm>
#include <cmath>
#include <numbers>

#include "geometry/cell_grid.h"
#include "geometry/check.h"

namespace beampack {

ContactGeometry contact_geometry(double d, double ri, double rj) {
  const double r_small = std::min(ri, rj);
  const double r_large = std::max(ri, rj);
  if (!(d < ri + rj)) return {0.0, d};  // no contact: no area, and the distance is never 0
  if (d <= r_large - r_small) {
    return {std::numbers::pi * r_small * r_small,
            std::max(d, kMinContactDistanceFraction * r_small)};
  }
  // Each factor is formed so that it is symmetric in (ri, rj) and cannot underflow for tiny d.
  const double sum = ri + rj, diff = r_large - r_small;
  const double a2 = 0.25 * (sum - d) * (sum + d) * ((d - diff) / d) * ((d + diff) / d);
  // The contact disk is never wider than the smaller sphere's equator.
  // (sum - d) and (d - diff) round by ~eps r_large, which r_small^2 need not dwarf.
  BEAMPACK_DCHECK(a2 <= r_small * r_small + 1e-14 * r_large * sum,
                  "contact of radii %.17g and %.17g m at distance %.17g m: a^2 = %.17g", ri, rj, d,
                  a2);
  return {std::numbers::pi * std::max(a2, 0.0), std::max(d, kMinContactDistanceFraction * r_small)};
}

namespace {

// Overlapping pairs between the particles of `cell` and those of its neighbour cells, each pair
// once (from the slot with the smaller particle id).
void contacts_of_cell(const CellGrid& grid, std::size_t cell, std::vector<Contact>& out) {
  for (std::uint32_t a = grid.begin(cell); a < grid.end(cell); ++a) {
    const std::uint32_t i = grid.id(a);
    const Vec3& ci = grid.centre(a);
    const double ri = grid.radius(a);
    grid.for_each_neighbour_cell(cell, [&](std::size_t other) {
      for (std::uint32_t b = grid.begin(other); b < grid.end(other); ++b) {
        const std::uint32_t j = grid.id(b);
        if (j <= i) continue;
        const double rj = grid.radius(b);
        const double d2 = (grid.centre(b) - ci).squaredNorm();
        if (!(d2 < (ri + rj) * (ri + rj))) continue;
        // The overlap test again on the distance itself, as contact_geometry makes it: for
        // touching spheres d^2 may round below (ri + rj)^2 while d rounds to ri + rj, a pair with
        // no area (a close-packed lattice read from a file has hundreds).
        const double d = std::sqrt(d2);
        if (!(d < ri + rj)) continue;
        const ContactGeometry g = contact_geometry(d, ri, rj);
        out.push_back({i, j, g.area, g.distance});
      }
    });
  }
}

}  // namespace

std::vector<Contact> find_contacts(const Particles& particles) {
  if (particles.alive_count() < 2) return {};
  const CellGrid grid(particles, 2.0 * particles.max_radius());

  // Fixed-size blocks of cells, then one sort on the unique keys (i, j): the result does not
  // depend on the thread count or on the scheduling.
  constexpr std::size_t kBlock = 1024;
  const std::size_t blocks = (grid.cell_count() + kBlock - 1) / kBlock;
  std::vector<std::vector<Contact>> per_block(blocks);
  tbb::parallel_for(std::size_t{0}, blocks, [&](std::size_t b) {
    const std::size_t last = std::min(grid.cell_count(), (b + 1) * kBlock);
    for (std::size_t cell = b * kBlock; cell < last; ++cell)
      contacts_of_cell(grid, cell, per_block[b]);
  });
  std::size_t total = 0;
  for (const auto& v : per_block) total += v.size();
  std::vector<Contact> contacts;
  contacts.reserve(total);
  for (const auto& v : per_block) contacts.insert(contacts.end(), v.begin(), v.end());
  tbb::parallel_sort(contacts.begin(), contacts.end(), [](const Contact& a, const Contact& b) {
    return a.i != b.i ? a.i < b.i : a.j < b.j;
  });
  return contacts;
}

}  // namespace beampack
