#include "engine/fresnel.h"

#include <algorithm>
#include <cmath>

namespace beampack {

Reflectances reflectance_components(double cos_i, double n_hat, double mu_hat) {
  const FresnelFractions f = fresnel_fractions(cos_i, n_hat, mu_hat);
  if (f.total) return {1.0, 1.0};
  const double r_par = f.par_num / f.par_den, r_perp = f.perp_num / f.perp_den;
  return {r_par * r_par, r_perp * r_perp};
}

double reflectance_polarised(double cos_i, double n_hat, double mu_hat, double gamma) {
  const Reflectances r = reflectance_components(cos_i, n_hat, mu_hat);
  const double c = std::cos(gamma), s = std::sin(gamma);
  return r.parallel * c * c + r.perpendicular * s * s;
}

PolarisedReflection reflect_polarised(const Vec3& d, const Vec3& n, const Vec3& e, double n_hat,
                                      double mu_hat) {
  const FresnelFractions f = fresnel_fractions(-d.dot(n), n_hat, mu_hat);
  const double r_par = f.total ? 1.0 : f.par_num / f.par_den;
  const double r_perp = f.total ? 1.0 : f.perp_num / f.perp_den;
  Vec3 s = d.cross(n);
  const double length = s.norm();
  s = length > 1e-12 ? Vec3(s / length) : e;  // normal incidence: any s across d, R_par = R_perp
  const double a_par = e.dot(s.cross(d)), a_perp = e.dot(s);
  const Vec3 reflected = reflect(d, n);
  const Vec3 field = r_par * a_par * s.cross(reflected) + r_perp * a_perp * s;
  const double norm = field.norm();
  // At most 1: at a tangent hit both amplitudes are 1 and the field's split rounds up (by ~1e-15),
  // which made the absorbed share a tiny negative energy, refused mid-run.
  const double reflectance =
      std::min(r_par * r_par * a_par * a_par + r_perp * r_perp * a_perp * a_perp, 1.0);
  // R = 0: nothing goes on; any unit field will do.
  return {reflectance, norm > 0.0 ? Vec3(field / norm) : s};
}

Reflectances reflectance_components(double cos_i, std::complex<double> n_hat, double mu_hat) {
  using C = std::complex<double>;
  cos_i = std::clamp(cos_i, 0.0, 1.0);
  const C n2 = n_hat * n_hat;
  // Principal branch: Im >= 0, the decaying wave; for n = 1 exactly cos_i itself (as real n does).
  const C root = n2 == C(1.0) ? C(cos_i) : std::sqrt((n2 - 1.0) + cos_i * cos_i);
  const C a = n2 / mu_hat * cos_i;
  const C b = root / mu_hat;
  // n = 1 at exact grazing makes both fractions 0/0: their limit, as in the real case.
  const double limit = std::norm((1.0 - mu_hat) / (1.0 + mu_hat));
  const double r_par = std::abs(a + root) > 0.0 ? std::norm((a - root) / (a + root)) : limit;
  const double r_perp = std::abs(cos_i + b) > 0.0 ? std::norm((cos_i - b) / (cos_i + b)) : limit;
  return {std::min(r_par, 1.0), std::min(r_perp, 1.0)};
}

double reflectance(double cos_i, std::complex<double> n_hat, double mu_hat) {
  const Reflectances r = reflectance_components(cos_i, n_hat, mu_hat);
  return 0.5 * (r.parallel + r.perpendicular);
}

}  // namespace beampack
