// Fresnel reflectance (2.14)-(2.25) against closed forms and published values.
#include <gtest/gtest.h>

#include <cmath>
#include <complex>
#include <cstdint>
#include <numbers>

#include "engine/fresnel.h"

using namespace beampack;

namespace {
double cos_deg(double deg) {
  return std::cos(deg * std::numbers::pi / 180.0);
}
}  // namespace

TEST(Fresnel, NormalIncidenceIsSquaredIndexContrast) {
  for (double n : {1.0, 1.2, 1.4, 2.0, 4.0, 20.0}) {
    const double expected = std::pow((n - 1) / (n + 1), 2);
    EXPECT_NEAR(reflectance(1.0, n), expected, 1e-15) << "n_hat = " << n;
  }
}

TEST(Fresnel, BrewsterAngleCancelsParallelComponent) {
  for (double n : {1.4, 2.0, 20.0}) {
    const double brewster = std::atan(n);
    const Reflectances r = reflectance_components(std::cos(brewster), n);
    EXPECT_NEAR(r.parallel, 0.0, 1e-15) << "n_hat = " << n;
    EXPECT_GT(r.perpendicular, 0.0);
  }
}

TEST(Fresnel, GrazingIncidenceReflectsEverything) {
  for (double n : {1.01, 1.4, 20.0}) {
    EXPECT_NEAR(reflectance(0.0, n), 1.0, 1e-15);
    EXPECT_GT(reflectance(1e-6, n), 1.0 - 1e-4);
  }
}

TEST(Fresnel, MatchedMediumIsTransparent) {
  for (double deg = 0; deg <= 90; deg += 0.5) EXPECT_EQ(reflectance(cos_deg(deg), 1.0, 1.0), 0.0);
  EXPECT_EQ(reflectance(0.3, std::complex<double>(1.0, 0.0)), 0.0);
}

TEST(Fresnel, LargeIndexReflectsEverything) {
  // For n_hat >> 1, r_par ~ (n cos - 1)/(n cos + 1) and r_perp ~ (cos - n)/(cos + n), so the
  // absorbed share 1 - R ~ 2/(n cos) + 2 cos/n: it falls like 1/n at every angle.
  for (double deg : {0.0, 30.0, 60.0, 85.0}) {
    const double c = cos_deg(deg);
    for (double n : {1e3, 1e6}) {
      const double absorbed = 1.0 - reflectance(c, n);
      const double asymptote = 2.0 / (n * c) + 2.0 * c / n;
      // The expansion drops terms of relative size 2/(n cos) (at normal incidence 4n/(n+1)^2).
      EXPECT_NEAR(absorbed, asymptote, 3.0 / (n * c) * asymptote)
          << "n_hat = " << n << ", deg = " << deg;
    }
  }
}

// Across the whole accepted range of index and permeability (and beyond it in n_hat, for the
// one-division form's own sake) the reflectance is a number in [0, 1]. The one-division form
// overflowed where p^2 q^2 came within a factor 2 of the largest double: n_hat ~ 2.1e51 at normal
// incidence, or mu_hat ~ 9.74e73 with n_hat = 1e6, both gave R = inf.
TEST(Fresnel, ReflectanceStaysInZeroOneAtTheExtremes) {
  for (double n : {1e-6, 0.5, 1.4, 1e3, kMaxIndex, 2.12e51, 2.3e51, 5e51, 1e100})
    for (double log_mu = std::log10(kMinMu); log_mu <= std::log10(kMaxMu); log_mu += 0.01)
      for (double c : {1.0, 0.999, 0.5, 0.1, 1e-3, 0.0}) {
        const double mu = std::pow(10.0, log_mu);
        const double r = reflectance(c, n, mu);
        ASSERT_TRUE(r >= 0.0 && r <= 1.0) << "n " << n << " mu " << mu << " cos " << c << ": " << r;
      }
  // The window itself, finely: mu_hat from 9.70e73 to 9.78e73 at n_hat = 1e6, normal incidence.
  for (double mu = 9.70e73; mu < 9.78e73; mu += 1e69) {
    const double r = reflectance(1.0, kMaxIndex, mu);
    ASSERT_TRUE(r >= 0.0 && r <= 1.0) << "mu " << mu << ": " << r;
  }
  for (double n = 2.10e51; n < 2.40e51; n += 1e48) {
    const double r = reflectance(1.0, n);
    ASSERT_TRUE(r >= 0.0 && r <= 1.0) << "n " << n << ": " << r;
  }
}

TEST(Fresnel, ReflectanceIsBoundedAndFinite) {
  for (double n : {0.2, 0.7, 1.0, 1.4, 3.0, 1e3})
    for (double mu : {0.5, 1.0, 2.0})
      for (double c = 0.0; c <= 1.0; c += 1.0 / 64) {
        const double r = reflectance(c, n, mu);
        ASSERT_TRUE(std::isfinite(r));
        ASSERT_GE(r, 0.0);
        ASSERT_LE(r, 1.0);
      }
}

// mu_hat != 1, values computed by hand from (2.14): at normal incidence both components reduce to
// ((n - mu)/(n + mu))^2; at 45 degrees with n = 1.5, mu = 2:
//   sqrt(n^2 - sin^2) = sqrt(1.75) = 1.3228757, r_par = (1.125 cos45 - 1.3228757) / (... + ...)
//   = -0.2489553, r_perp = (cos45 - 1.3228757/2) / (cos45 + 1.3228757/2) = 0.0333706,
//   R = (0.0619787 + 0.0011136) / 2 = 0.0315463.
TEST(Fresnel, MagneticPermeabilityRatioMatchesHandValues) {
  EXPECT_NEAR(reflectance(1.0, 1.5, 2.0), std::pow(0.5 / 3.5, 2), 1e-15);
  EXPECT_NEAR(reflectance(cos_deg(45), 1.5, 2.0), 0.0315463, 1e-7);
  // mu_hat = n_hat makes the perpendicular component vanish at normal incidence.
  EXPECT_NEAR(reflectance(1.0, 1.7, 1.7), 0.0, 1e-15);
}

TEST(Fresnel, TotalReflectionBeyondCriticalAngle) {
  const double n = 0.8;  // (2.23)-(2.24): sin^2 > n^2
  const double critical = std::asin(n);
  EXPECT_EQ(reflectance(std::cos(critical + 1e-3), n), 1.0);
  EXPECT_LT(reflectance(std::cos(critical - 1e-2), n), 1.0);
  // The complex formulas give the same |r| = 1 without the special case.
  EXPECT_NEAR(reflectance(std::cos(critical + 0.2), std::complex<double>(n, 0.0)), 1.0, 1e-14);
}

TEST(Fresnel, PolarisedAveragesToUnpolarised) {
  for (double deg : {0.0, 20.0, 56.0, 80.0}) {
    const double c = cos_deg(deg);
    const Reflectances r = reflectance_components(c, 1.4);
    EXPECT_DOUBLE_EQ(reflectance_polarised(c, 1.4, 1.0, 0.0), r.parallel);
    EXPECT_DOUBLE_EQ(reflectance_polarised(c, 1.4, 1.0, std::numbers::pi / 2), r.perpendicular);
    EXPECT_NEAR(reflectance_polarised(c, 1.4, 1.0, std::numbers::pi / 4), reflectance(c, 1.4),
                1e-15);
  }
}

TEST(Fresnel, ComplexIndexReducesToRealForZeroExtinction) {
  for (double deg = 0; deg < 90; deg += 7.5) {
    const double c = cos_deg(deg);
    EXPECT_NEAR(reflectance(c, std::complex<double>(1.4, 0.0)), reflectance(c, 1.4), 1e-14);
    EXPECT_NEAR(reflectance(c, std::complex<double>(1.5, 0.0), 2.0), reflectance(c, 1.5, 2.0),
                1e-14);
  }
}

// Silver at 632.8 nm (1.96 eV): n = 0.056, k = 4.276, P. B. Johnson and R. W. Christy,
// "Optical constants of the noble metals", Phys. Rev. B 6, 4370 (1972). Normal-incidence
// reflectance ((n-1)^2 + k^2) / ((n+1)^2 + k^2) = 0.98845, the ~98.9% quoted for silver mirrors.
TEST(Fresnel, SilverReflectanceMatchesPublishedIndex) {
  const std::complex<double> silver(0.056, 4.276);
  EXPECT_NEAR(reflectance(1.0, silver), 0.988453, 1e-6);
  // Abeles' identity holds for any complex index at 45 degrees: R_par = R_perp^2.
  const Reflectances r45 = reflectance_components(cos_deg(45), silver);
  EXPECT_NEAR(r45.parallel, r45.perpendicular * r45.perpendicular, 1e-14);
  EXPECT_GT(reflectance(cos_deg(60), silver), 0.97);
}

// Oblique incidence on absorbing media against (2.14) written out here in long double complex
// arithmetic: with w = sqrt(n^2 - sin^2), r_par = (n^2 cos - mu w) / (n^2 cos + mu w) and
// r_perp = (mu cos - w) / (mu cos + w). For k > 0 the principal root has Im w > 0, the wave that
// decays into the metal; a root of the wrong sign turns r into 1 / r, which Abeles' identity and
// normal incidence cannot see. Indices at 632.8 nm: gold 0.197 + 3.09i, aluminium 1.2 + 7.26i
// (Rakic 1995), silver as above; and a weakly absorbing dielectric.
TEST(Fresnel, ComplexIndexAtObliqueIncidenceMatchesTheFormulasInLongDouble) {
  using C = std::complex<long double>;
  const std::complex<double> media[] = {{0.197, 3.09}, {1.2, 7.26}, {0.056, 4.276}, {1.5, 0.1}};
  for (const std::complex<double> n : media)
    for (const double mu : {1.0, 2.0})
      for (const double deg : {10.0, 30.0, 45.0, 60.0, 75.0, 85.0, 89.9}) {
        const long double c =
            std::cos(static_cast<long double>(deg) * std::numbers::pi_v<long double> / 180);
        const C n2 = C(n) * C(n), w = std::sqrt(n2 - (1 - c * c));
        const long double m = mu;
        const long double r_par = std::norm((n2 * c - m * w) / (n2 * c + m * w));
        const long double r_perp = std::norm((m * c - w) / (m * c + w));
        const Reflectances r = reflectance_components(double(c), n, mu);
        EXPECT_NEAR(r.parallel, double(r_par), 1e-12) << n << " mu " << mu << " at " << deg;
        EXPECT_NEAR(r.perpendicular, double(r_perp), 1e-12) << n << " mu " << mu << " at " << deg;
        EXPECT_LT(r.perpendicular, 1.0) << n << " at " << deg;  // absorbing: never a mirror
      }
}

TEST(Fresnel, AbelesIdentityHoldsForDielectrics) {
  for (double n : {1.2, 1.4, 3.0}) {
    const Reflectances r = reflectance_components(cos_deg(45), n);
    EXPECT_NEAR(r.parallel, r.perpendicular * r.perpendicular, 1e-15);
  }
}

TEST(Fresnel, SpecularReflectionMirrorsTheNormalComponent) {
  const Vec3 d = Vec3(1, -2, 0.5).normalized();
  const Vec3 n = Vec3(0.3, 1, -0.2).normalized();
  const Vec3 r = reflect(d, n);
  EXPECT_NEAR(r.norm(), 1.0, 1e-15);
  EXPECT_NEAR(r.dot(n), -d.dot(n), 1e-15);
  EXPECT_NEAR((r - r.dot(n) * n - (d - d.dot(n) * n)).norm(), 0.0, 1e-15);
}

// A linearly polarised ray reflected: closed forms in the plane of incidence xy (d = +x, normal
// at incidence theta), then a seeded property test over random geometry.
// At a tangent hit both amplitudes are 1 and the split of the field rounds: R must still be at
// most 1 (it reached 1 + 1.1e-15 in 29% of such hits, and the absorbed share 1 - R turned into a
// tiny negative energy that stopped the run).
TEST(Fresnel, PolarisedReflectanceAtATangentHitIsAtMostOne) {
  std::uint64_t state = 7;
  auto uniform = [&] {  // in [-1, 1)
    state = state * 6364136223846793005ull + 1442695040888963407ull;
    return double(state >> 11) * 0x1p-52 - 1.0;
  };
  int at_one = 0;
  for (int k = 0; k < 20000; ++k) {
    const Vec3 n = Vec3(uniform(), uniform(), uniform()).normalized();
    Vec3 d = Vec3(uniform(), uniform(), uniform()).cross(n).normalized();  // across n: tangent
    d -= d.dot(n) * n;
    d.normalize();
    const Vec3 e = d.cross(Vec3(uniform(), uniform(), uniform())).normalized();  // across d
    const PolarisedReflection r = reflect_polarised(d, n, e, 1.4);
    ASSERT_LE(r.reflectance, 1.0) << k;
    EXPECT_GE(r.reflectance, 0.999999) << k;  // grazing: nearly everything is reflected
    at_one += r.reflectance == 1.0;
  }
  EXPECT_GT(at_one, 0);  // grazing exactly: R = 1 (to the clamp) for some
}

TEST(Fresnel, PolarisedReflectionSplitsTheFieldOnThePlaneOfIncidence) {
  const double n_hat = 3.0, theta = 50.0 * std::numbers::pi / 180.0;
  const Vec3 d(1, 0, 0), n(-std::cos(theta), std::sin(theta), 0);  // plane of incidence: xy
  const Reflectances r = reflectance_components(std::cos(theta), n_hat);
  const Vec3 reflected = reflect(d, n);
  // Field across the plane (s): R_perp, and it stays across the plane, turned over (r_perp < 0).
  const PolarisedReflection s = reflect_polarised(d, n, Vec3(0, 0, 1), n_hat);
  EXPECT_NEAR(s.reflectance, r.perpendicular, 1e-15);
  EXPECT_NEAR((s.field - Vec3(0, 0, -1)).norm(), 0.0, 1e-15);
  // Field in the plane (p): R_par, and it stays in the plane, across the reflected ray.
  const PolarisedReflection p = reflect_polarised(d, n, Vec3(0, 1, 0), n_hat);
  EXPECT_NEAR(p.reflectance, r.parallel, 1e-15);
  EXPECT_NEAR(p.field.z(), 0.0, 1e-15);
  EXPECT_NEAR(p.field.dot(reflected), 0.0, 1e-15);
  EXPECT_NEAR(p.field.norm(), 1.0, 1e-15);
  // At 45 degrees to the plane: the unpolarised mean.
  const PolarisedReflection half = reflect_polarised(d, n, Vec3(0, 1, 1).normalized(), n_hat);
  EXPECT_NEAR(half.reflectance, 0.5 * (r.parallel + r.perpendicular), 1e-15);
  // Brewster's angle, tan theta = n: p-light is not reflected at all.
  const double brewster = std::atan(n_hat);
  const Vec3 nb(-std::cos(brewster), std::sin(brewster), 0);
  EXPECT_NEAR(reflect_polarised(d, nb, Vec3(0, 1, 0), n_hat).reflectance, 0.0, 1e-15);
  // Normal incidence: R = ((n - 1) / (n + 1))^2 and the field comes back turned over.
  const PolarisedReflection normal = reflect_polarised(d, Vec3(-1, 0, 0), Vec3(0, 0.6, 0.8), n_hat);
  EXPECT_NEAR(normal.reflectance, std::pow((n_hat - 1) / (n_hat + 1), 2), 1e-15);
  EXPECT_NEAR((normal.field - Vec3(0, -0.6, -0.8)).norm(), 0.0, 1e-15);
}

TEST(Fresnel, PolarisedReflectionPropertiesOnRandomGeometry) {
  std::uint64_t state = 20131;
  auto uniform = [&] {  // splitmix64: a small seeded generator for the test itself
    state += 0x9E3779B97F4A7C15ull;
    std::uint64_t z = state;
    z = (z ^ (z >> 30)) * 0xBF58476D1CE4E5B9ull;
    z = (z ^ (z >> 27)) * 0x94D049BB133111EBull;
    return double((z ^ (z >> 31)) >> 11) * 0x1.0p-53;
  };
  auto unit = [&] {
    const Vec3 v(uniform() - 0.5, uniform() - 0.5, uniform() - 0.5);
    return Vec3(v.normalized());
  };
  for (int k = 0; k < 2000; ++k) {
    const Vec3 d = unit();
    Vec3 n = unit();
    if (n.dot(d) > 0) n = -n;  // an outside hit
    const Vec3 e = d.cross(unit()).normalized(), e_across = d.cross(e);
    const double n_hat = 1.0 + 10.0 * uniform(), cos_i = -d.dot(n);
    const PolarisedReflection a = reflect_polarised(d, n, e, n_hat);
    const PolarisedReflection b = reflect_polarised(d, n, e_across, n_hat);
    const Reflectances r = reflectance_components(cos_i, n_hat);
    // Two crossed fields carry unpolarised light: their reflectances add to R_par + R_perp.
    EXPECT_NEAR(a.reflectance + b.reflectance, r.parallel + r.perpendicular, 1e-13) << k;
    EXPECT_GE(a.reflectance, std::min(r.parallel, r.perpendicular) - 1e-15) << k;
    EXPECT_LE(a.reflectance, std::max(r.parallel, r.perpendicular) + 1e-15) << k;
    // The reflected field is a unit vector across the reflected ray.
    EXPECT_NEAR(a.field.norm(), 1.0, 1e-12) << k;
    EXPECT_NEAR(a.field.dot(reflect(d, n)), 0.0, 1e-12) << k;
  }
}

// No interface (n = 1, mu = 1) reflects nothing at any angle, exact grazing and an underflowing
// cos^2 included (it used to take the total-reflection branch there: R = 1), in the real and the
// complex formulas (the complex one gave 0/0 = NaN).
TEST(Fresnel, NoInterfaceReflectsNothingEvenAtGrazing) {
  for (double c : {0.0, 1e-200, 1e-160, 1e-17, 0.5, 1.0}) {
    EXPECT_EQ(reflectance(c, 1.0), 0.0) << c;
    EXPECT_EQ(reflectance(c, std::complex<double>(1.0, 0.0)), 0.0) << c;
  }
  // With mu != 1 the grazing limit is ((1 - mu) / (1 + mu))^2 for both components.
  const double limit = std::pow((1.0 - 2.0) / (1.0 + 2.0), 2);
  EXPECT_NEAR(reflectance(0.0, 1.0, 2.0), limit, 1e-15);
  EXPECT_NEAR(reflectance(1e-9, 1.0, 2.0), limit, 1e-8);
}
