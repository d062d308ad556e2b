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
  return polarised_reflectance(reflectance_components(cos_i, n_hat, mu_hat), std::cos(gamma),
                               std::sin(gamma));
}

Reflectances reflectance_components(double cos_i, std::complex<double> n_hat, double mu_hat) {
  using C = std::complex<double>;
  cos_i = std::clamp(cos_i, 0.0, 1.0);
  const C n2 = n_hat * n_hat;
  const C root = std::sqrt((n2 - 1.0) + cos_i * cos_i);  // principal branch: Im >= 0, the decaying wave
  const C a = n2 / mu_hat * cos_i;
  const C b = root / mu_hat;
  const double r_par = std::norm((a - root) / (a + root));
  const double r_perp = std::norm((cos_i - b) / (cos_i + b));
  return {std::min(r_par, 1.0), std::min(r_perp, 1.0)};
}

double reflectance(double cos_i, std::complex<double> n_hat, double mu_hat) {
  const Reflectances r = reflectance_components(cos_i, n_hat, mu_hat);
  return 0.5 * (r.parallel + r.perpendicular);
}

}  // namespace beampack
