#pragma once
// Fresnel reflectance at a particle surface, section 2.4 of the paper. Pure functions.
#include <complex>

#include "geometry/vec3.h"

namespace beampack {

struct Reflectances {
  double parallel;       // R_par = r_par^2, (2.13)-(2.14)
  double perpendicular;  // R_perp = r_perp^2
};

// R_par and R_perp for incidence cos_i in [0, 1] on a medium of relative index n_hat and relative
// permeability mu_hat (2.14). Where sin^2 > n_hat^2 (only for n_hat < 1) both are 1 (2.23)-(2.24).
Reflectances reflectance_components(double cos_i, double n_hat, double mu_hat = 1.0);

// Unpolarised reflectance (2.22)/(2.25): (R_par + R_perp) / 2.
double reflectance(double cos_i, double n_hat, double mu_hat = 1.0);

// Linear polarisation at angle gamma to the plane of incidence (2.18):
// R = R_par cos^2(gamma) + R_perp sin^2(gamma).
double reflectance_polarised(double cos_i, double n_hat, double mu_hat, double gamma);

// Complex index n + i k (metals), same formulas in complex arithmetic (pbrt's FrComplex idea);
// an extension beyond the paper. Reduces to the real version for k = 0.
Reflectances reflectance_components(double cos_i, std::complex<double> n_hat, double mu_hat = 1.0);
double reflectance(double cos_i, std::complex<double> n_hat, double mu_hat = 1.0);

// Specular reflection d' = d - 2 (d.n) n.
inline Vec3 reflect(const Vec3& d, const Vec3& n) { return d - 2.0 * d.dot(n) * n; }

}  // namespace beampack
