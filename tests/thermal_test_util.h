#pragma once
// Small scenes shared by the thermal tests.
#include <Eigen/Dense>
#include <cmath>
#include <numbers>
#include <vector>

#include "geometry/contact.h"
#include "geometry/particles.h"
#include "thermal/material.h"

namespace beampack::test {

// m C / M of a sphere of radius r in its solid phase.
inline double solid_capacity(const Material& m, double r, double time_scaling) {
  return m.density * 4.0 / 3.0 * std::numbers::pi * r * r * r * m.c_solid / time_scaling;
}

// A row of n spheres along x, spacing a, radius 0.6 a: each touches its neighbours only.
inline Particles chain(int n, double a, double theta0 = 300.0) {
  Particles p;
  for (int k = 0; k < n; ++k) p.add(Vec3(a * (k + 0.5), 0.5 * a, 0.5 * a), 0.6 * a, 0, theta0);
  return p;
}

// The conduction matrix L of (3.2), assembled densely by hand from the contacts: each contact's
// conductance_of(contact) on both ends' diagonals, its negative between them.
template <class Conductance>
Eigen::MatrixXd dense_conduction(Eigen::Index n, const std::vector<Contact>& contacts,
                                 Conductance conductance_of) {
  Eigen::MatrixXd l = Eigen::MatrixXd::Zero(n, n);
  for (const Contact& ct : contacts) {
    const double g = conductance_of(ct);
    l(ct.i, ct.i) += g, l(ct.j, ct.j) += g, l(ct.i, ct.j) -= g, l(ct.j, ct.i) -= g;
  }
  return l;
}

inline std::vector<double> constant(std::size_t n, double v) {
  return std::vector<double>(n, v);
}

}  // namespace beampack::test
