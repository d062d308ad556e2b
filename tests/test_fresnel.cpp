// Fresnel reflectance (2.14)-(2.25) against closed forms and published values.
#include <gtest/gtest.h>

#include <cmath>
#include <numbers>

#include "engine/fresnel.h"

using namespace beampack;

namespace {
double cos_deg(double deg) { return std::cos(deg * std::numbers::pi / 180.0); }
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
      EXPECT_NEAR(absorbed, asymptote, 3.0 / (n * c) * asymptote) << "n_hat = " << n << ", deg = " << deg;
    }
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
