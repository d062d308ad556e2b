#pragma once
// Conduction between touching spheres (3.2) and with isothermal walls (1.1), assembled as the
// sparse matrix L + W such that the net heat flow into the particles is
// Q(theta) = b - (L + W) theta.
#include <Eigen/SparseCore>
#include <vector>

#include "../geometry/contact.h"
#include "../geometry/particles.h"
#include "material.h"

namespace beampack {

// G_ij = K_ij A_ij / |r_j - r_i| of (3.2), with the pair average K_ij = (K_i + K_j) / 2
// (paper, footnote 8). W/K.
inline double conductance(double k_i, double k_j, double area, double distance) {
  return 0.5 * (k_i + k_j) * area / distance;
}

// An isothermal wall: the plane x[axis] = position held at `temperature`. A particle whose surface
// lies within `reach` of the plane (|x_axis - position| - R <= reach) exchanges
// g (theta_w - theta_i) with it (1.1). One particle between two walls is the lumped model (1.2).
struct Wall {
  int axis = 0;              // 0: x, 1: y, 2: z
  double position = 0;       // m
  double reach = 0;          // m
  double temperature = 300;  // theta_w, K
  // W/K per touching particle. < 0: pi K_i R_i, i.e. (3.2) with the sphere's cross-section
  // pi R^2 as contact area and its radius R as conduction length.
  double conductance = -1;

  void validate(const std::string& prefix = "thermal.wall") const;
};

// Whether particle i lies within the wall's reach (its surface at most `reach` from the wall).
bool touches(const Wall& w, const Particles& p, std::size_t i);

// Per particle: total wall conductance sum_w g_w (W/K) and sum_w g_w theta_w (W).
struct WallCoupling {
  std::vector<double> conductance;
  std::vector<double> source;
  bool any() const;
};
WallCoupling wall_coupling(const Particles& particles, const std::vector<Material>& materials,
                           const std::vector<Wall>& walls);

// One G_ij per contact, by material id; all are 0 when every K is 0. A contact with a NaN or
// negative area or a distance <= 0 gives NaN, a negative or an inf, which ThermalModel::
// set_contacts refuses (find_contacts makes none).
std::vector<double> contact_conductances(const Particles& particles,
                                         const std::vector<Material>& materials,
                                         const std::vector<Contact>& contacts);

// L + W over all particles. Contacts with a dead end and walls of dead particles contribute
// explicit zeros, so the sparsity pattern depends on the contact list only: a vaporisation keeps
// the symbolic factorisation valid. Every diagonal entry is stored.
Eigen::SparseMatrix<double> conduction_matrix(const Particles& particles,
                                              const std::vector<Contact>& contacts,
                                              const std::vector<double>& g,
                                              const std::vector<double>& wall_g);

}  // namespace beampack
