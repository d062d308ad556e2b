#pragma once
// Fresnel reflectance at a particle surface, section 2.4 of the paper. Pure functions.
#include <algorithm>
#include <cmath>
#include <complex>
#include <limits>

#include "../geometry/vec3.h"

namespace beampack {

// The indices (real and imaginary parts) and relative permeabilities the optics accept: an index
// of 1e6 is a mirror to 1e-6 already, and far beyond these the terms of (2.14) overflow.
constexpr double kMaxIndex = 1e6;
constexpr double kMinMu = 1e-100, kMaxMu = 1e100;

struct Reflectances {
  double parallel;       // R_par = r_par^2, (2.13)-(2.14)
  double perpendicular;  // R_perp = r_perp^2
};

// The amplitude ratios of (2.14) as fractions, r_par = par_num / par_den and r_perp = perp_num /
// perp_den, both sides multiplied by mu_hat so that no division precedes the last one:
// r_par = (n^2 cos_i - mu n cos_t) / (n^2 cos_i + mu n cos_t),
// r_perp = (mu cos_i - n cos_t) / (mu cos_i + n cos_t), with n cos_t = sqrt(n^2 - sin^2).
// total: sin^2 > n_hat^2 (only for n_hat < 1), total reflection (2.23)-(2.24).
struct FresnelFractions {
  double par_num, par_den, perp_num, perp_den;
  bool total;
};
inline FresnelFractions fresnel_fractions(double cos_i, double n_hat, double mu_hat) {
  cos_i = std::clamp(cos_i, 0.0, 1.0);
  const double n2 = n_hat * n_hat;
  // n^2 - sin^2 written as (n^2 - 1) + cos^2: exact for n = 1 and free of the 1 - cos^2
  // cancellation near grazing incidence.
  const double n2_minus_sin2 = (n2 - 1.0) + cos_i * cos_i;
  if (n2_minus_sin2 <= 0.0) {
    if (n_hat < 1.0) return {1.0, 1.0, 1.0, 1.0, true};
    // n = 1 at exact grazing (or cos^2 underflowed): the limit, r_par = (1 - mu) / (1 + mu) =
    // -r_perp, which is 0 for mu = 1 (no interface reflects nothing), not total reflection.
    return {1.0 - mu_hat, 1.0 + mu_hat, mu_hat - 1.0, mu_hat + 1.0, false};
  }
  // n_hat cos(theta_t); for n = 1 exactly cos_i itself (the square root of cos^2 loses it to
  // rounding, or to underflow near grazing).
  const double root = n2 == 1.0 ? cos_i : std::sqrt(n2_minus_sin2);
  const double a = n2 * cos_i, b = mu_hat * root, c = mu_hat * cos_i;
  return {a - b, a + b, c - root, c + root, false};
}

// R_par and R_perp for incidence cos_i in [0, 1] on a medium of relative index n_hat and relative
// permeability mu_hat (2.14). Where sin^2 > n_hat^2 (only for n_hat < 1) both are 1 (2.23)-(2.24).
Reflectances reflectance_components(double cos_i, double n_hat, double mu_hat = 1.0);

// Unpolarised reflectance (2.22)/(2.25): (R_par + R_perp) / 2. Inline with a single division:
// the tracer calls it at every hit.
inline double reflectance(double cos_i, double n_hat, double mu_hat = 1.0) {
  const FresnelFractions f = fresnel_fractions(cos_i, n_hat, mu_hat);
  if (f.total) return 1.0;
  const double p2 = f.par_den * f.par_den, q2 = f.perp_den * f.perp_den, den = p2 * q2;
  // |num| <= |den| for each fraction, so the numerator below is at most 2 den: finite when den
  // is at most half the largest double. Beyond (n_hat ~ 2e51, or mu_hat ~ 1e74 with n_hat = 1e6)
  // or below the normal range, two divisions.
  if (!(den >= std::numeric_limits<double>::min() &&
        den <= 0.5 * std::numeric_limits<double>::max())) {
    const Reflectances r = reflectance_components(cos_i, n_hat, mu_hat);
    return 0.5 * (r.parallel + r.perpendicular);
  }
  return 0.5 * (f.par_num * f.par_num * q2 + f.perp_num * f.perp_num * p2) / den;
}

// Linear polarisation at angle gamma to the plane of incidence (2.18):
// R = R_par cos^2(gamma) + R_perp sin^2(gamma).
double reflectance_polarised(double cos_i, double n_hat, double mu_hat, double gamma);

// A linearly polarised ray (unit field e, perpendicular to the unit direction d) reflected at a
// surface of outward unit normal n, real index n_hat >= 1: the field splits on s = d x n / |d x n|
// and p = s x d, so cos(gamma) = e.p in (2.18) and R = R_par (e.p)^2 + R_perp (e.s)^2; the
// reflected field is r_par (e.p) p' + r_perp (e.s) s with p' = s x d' (the sign convention under
// which normal and grazing reflection both return -e), normalised. At normal incidence s = e.
struct PolarisedReflection {
  double reflectance;
  Vec3 field;  // unit, perpendicular to the reflected direction
};
PolarisedReflection reflect_polarised(const Vec3& d, const Vec3& n, const Vec3& e, double n_hat,
                                      double mu_hat = 1.0);

// Complex index n + i k (metals), same formulas in complex arithmetic (pbrt's FrComplex idea);
// an extension beyond the paper. Reduces to the real version for k = 0.
Reflectances reflectance_components(double cos_i, std::complex<double> n_hat, double mu_hat = 1.0);
double reflectance(double cos_i, std::complex<double> n_hat, double mu_hat = 1.0);

// Specular reflection d' = d - 2 (d.n) n.
inline Vec3 reflect(const Vec3& d, const Vec3& n) {
  return d - 2.0 * d.dot(n) * n;
}

}  // namespace beampack
