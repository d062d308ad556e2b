#include "geometry/contact.h"

#include <tbb/parallel_for.h>

#include <algorithm>
#include <cmath>
#include <numbers>

#include "geometry/cell_grid.h"

namespace beampack {

ContactGeometry contact_geometry(double d, double ri, double rj) {
  const double r_small = std::min(ri, rj);
  const double r_large = std::max(ri, rj);
  if (!(d < ri + rj)) return {};
  if (d <= r_large - r_small) {
    return {std::numbers::pi * r_small * r_small,
            std::max(d, kMinContactDistanceFraction * r_small)};
  }
  const double sum = ri + rj, diff = ri - rj;
  const double a2 = (sum - d) * (sum + d) * (d - diff) * (d + diff) / (4.0 * d * d);
  return {std::numbers::pi * std::max(a2, 0.0), std::max(d, kMinContactDistanceFraction * r_small)};
}

namespace {

// Pairs (i, j > i) of particle i, in the order the 27 cells are visited, then sorted by j.
void contacts_of(const Particles& p, const CellGrid& grid, std::uint32_t i,
                 std::vector<Contact>& out) {
  const std::size_t first = out.size();
  grid.for_each_neighbour(p.centre[i], [&](std::uint32_t j) {
    if (j <= i) return;
    const double d = (p.centre[j] - p.centre[i]).norm();
    if (!(d < p.radius[i] + p.radius[j])) return;
    const ContactGeometry g = contact_geometry(d, p.radius[i], p.radius[j]);
    out.push_back({i, j, g.area, g.distance});
  });
  std::sort(out.begin() + first, out.end(),
            [](const Contact& a, const Contact& b) { return a.j < b.j; });
}

}  // namespace

std::vector<Contact> find_contacts(const Particles& particles) {
  const std::size_t n = particles.size();
  if (particles.alive_count() < 2) return {};
  const CellGrid grid(particles, 2.0 * particles.max_radius());

  // Fixed-size blocks, concatenated in block order: the result does not depend on threads.
  constexpr std::size_t kBlock = 4096;
  const std::size_t blocks = (n + kBlock - 1) / kBlock;
  std::vector<std::vector<Contact>> per_block(blocks);
  tbb::parallel_for(std::size_t{0}, blocks, [&](std::size_t b) {
    auto& out = per_block[b];
    for (std::size_t i = b * kBlock; i < std::min(n, (b + 1) * kBlock); ++i)
      if (particles.alive[i]) contacts_of(particles, grid, static_cast<std::uint32_t>(i), out);
  });
  std::size_t total = 0;
  for (const auto& v : per_block) total += v.size();
  std::vector<Contact> contacts;
  contacts.reserve(total);
  for (const auto& v : per_block) contacts.insert(contacts.end(), v.begin(), v.end());
  return contacts;
}

}  // namespace beampack
