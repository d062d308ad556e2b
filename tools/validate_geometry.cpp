// Closed-form cases of the optics functions and the geometry.
#include <cmath>
#include <complex>
#include <numbers>

#include "engine/fresnel.h"
#include "geometry/contact.h"
#include "geometry/ray_sphere.h"
#include "tools/validate.h"

namespace beampack::tools {

namespace {

// The complex index at oblique incidence, where cos_t enters through n^2 - sin^2 (at normal
// incidence any function of cos_i that is 1 there passes). Expected values from an independent
// computation (Python, complex doubles): the boundary conditions (tangential E and H continuous)
// solved as a 2x2 linear system per polarisation, the transmitted wave's normal wavenumber taken
// with Im >= 0 (decaying into the metal), eps = n^2 / mu; each checked against energy, R + T = 1
// with T the transmitted Poynting flux, to 4e-16. Tolerance 1e-13: the closed forms in doubles
// agree with them to 1e-16 (about 1000 ulps of margin for other compilers' complex arithmetic).
struct ComplexCase {
  const char* name;
  std::complex<double> index;
  double mu, degrees, expected;
};
std::vector<ComplexCase> complex_oblique_cases() {
  const std::complex<double> silver(0.056, 4.276), lossy(1.5, 0.3);
  return {
      {"Fresnel silver n=0.056+4.276i at 30 deg", silver, 1.0, 30, 0.988355259035536},
      {"Fresnel silver n=0.056+4.276i at 60 deg", silver, 1.0, 60, 0.986692528152554},
      {"Fresnel silver n=0.056+4.276i at 80 deg", silver, 1.0, 80, 0.986121586716753},
      {"Fresnel n=1.5+0.3i, mu=2 at 30 deg", lossy, 2.0, 30, 0.0296708571698307},
      {"Fresnel n=1.5+0.3i, mu=2 at 60 deg", lossy, 2.0, 60, 0.0910088992039025},
      {"Fresnel n=1.5+0.3i, mu=2 at 80 deg", lossy, 2.0, 80, 0.423142993508128},
  };
}

}  // namespace

std::vector<ValidationCase> optics_cases() {
  const double n = 1.4;
  const double brewster = std::atan(n);
  const std::complex<double> silver(0.056, 4.276);  // Johnson & Christy 1972, 632.8 nm
  std::vector<ValidationCase> cases{
      {"Fresnel normal incidence n=1.4: ((n-1)/(n+1))^2", std::pow((n - 1) / (n + 1), 2),
       reflectance(1.0, n), 1e-15},
      {"Fresnel Brewster angle n=1.4: R_parallel", 0.0,
       reflectance_components(std::cos(brewster), n).parallel, 1e-15},
      {"Fresnel grazing incidence n=1.4: R", 1.0, reflectance(0.0, n), 1e-15},
      {"Fresnel matched medium n=1, mu=1 at 60 deg: R", 0.0, reflectance(0.5, 1.0, 1.0), 0.0},
      {"Fresnel n=20 normal incidence", std::pow(19.0 / 21.0, 2), reflectance(1.0, 20.0), 1e-15},
      {"Fresnel mu=2, n=1.5 at 45 deg (hand value)", 0.0315463,
       reflectance(std::cos(std::numbers::pi / 4), 1.5, 2.0), 1e-7},
      {"Fresnel total reflection n=0.8 beyond critical angle", 1.0,
       reflectance(std::cos(std::asin(0.8) + 0.1), 0.8), 0.0},
      {"Fresnel silver n=0.056+4.276i normal incidence", 0.988453, reflectance(1.0, silver), 1e-6},
  };
  for (const ComplexCase& c : complex_oblique_cases())
    cases.push_back({c.name, c.expected,
                     reflectance(std::cos(c.degrees * std::numbers::pi / 180), c.index, c.mu),
                     1e-13});
  return cases;
}

std::vector<ValidationCase> geometry_cases() {
  const Vec3 c(0.3, -0.2, 0.1);
  const double r = 1e-3;
  const double far = 1e3;  // a ray from 1e6 radii away
  const double t = ray_sphere_entry(c - Vec3(far, 0, 0), Vec3(1, 0, 0), c, r);
  return {
      {"ray-sphere entry from 1e6 radii away: t", far - r, t, 1e-12 * far},
      {"ray-sphere from inside: no hit (1 = no hit)", 1.0,
       ray_sphere_entry(c, Vec3(0, 1, 0), c, r) == kNoHit ? 1.0 : 0.0, 0.0},
      {"contact area, equal spheres at distance R: 3 pi R^2 / 4", 0.75 * std::numbers::pi,
       contact_geometry(1.0, 1.0, 1.0).area, 1e-15},
      {"contact area, coincident centres: pi min(R)^2", std::numbers::pi * 0.25,
       contact_geometry(0.0, 0.5, 1.0).area, 1e-15},
  };
}

}  // namespace beampack::tools
