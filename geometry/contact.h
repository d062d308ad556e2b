#pragma once
// Contacts between overlapping spheres: the lens area (3.8)-(3.9) and the contact graph.
#include <cstdint>
#include <vector>

#include "particles.h"

namespace beampack {

// Smallest centre distance used for conduction, as a fraction of the smaller radius: coincident
// or nested spheres would otherwise divide by ~0 in (3.2). MODEL.md section 4.
constexpr double kMinContactDistanceFraction = 1e-2;

struct ContactGeometry {
  double area = 0.0;      // A_ij of (3.8); 0 when the spheres do not overlap
  double distance = 0.0;  // |r_i - r_j| for (3.2), floored for degenerate pairs; never 0
};

// Contact area and conduction distance of spheres with radii ri, rj whose centres are d apart.
// Regular overlap: A = pi (Ri^2 - Li^2) with Li of (3.9), evaluated in the product form
//   a^2 = ((Ri+Rj)^2 - d^2) (d^2 - (Ri-Rj)^2) / (4 d^2)
// which is the same quantity without the cancellation of Ri^2 - Li^2. The lens shrinks to a point
// as the smaller sphere approaches internal tangency, then the nested rule below takes over: the
// area jumps to pi min(R)^2 there (MODEL.md's rule; documented in the README).
// One sphere inside the other (d <= |Ri - Rj|, coincident centres included): the smaller
// sphere's full cross-section pi min(R)^2, distance floored at kMinContactDistanceFraction min(R).
// Symmetric in i and j; never NaN for finite non-negative inputs.
ContactGeometry contact_geometry(double d, double ri, double rj);

struct Contact {
  std::uint32_t i, j;  // i < j
  double area;
  double distance;
};

// Every overlapping pair of live particles, found with a uniform cell list (O(N) for bounded
// radius spread). Sorted by (i, j); identical for any thread count. After removals the list of the
// live particles is this one without theirs (ThermalModel::drop_removed_contacts): no new search.
std::vector<Contact> find_contacts(const Particles& particles);

}  // namespace beampack
