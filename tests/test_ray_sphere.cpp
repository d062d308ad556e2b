// Ray-sphere intersection: seeded property tests of the outside-hit rule and its precision.
#include <gtest/gtest.h>

#include <algorithm>

#include "geometry/random.h"
#include "geometry/ray_sphere.h"

using namespace beampack;

namespace {

Vec3 random_unit(Rng& rng) {
  for (;;) {
    const Vec3 v(rng.uniform(-1, 1), rng.uniform(-1, 1), rng.uniform(-1, 1));
    const double n2 = v.squaredNorm();
    if (n2 > 1e-4 && n2 <= 1) return v / std::sqrt(n2);
  }
}

}  // namespace

TEST(RaySphere, HitPointLiesOnTheSphereForRandomRays) {
  Rng rng(20131023);
  int hits = 0;
  for (int k = 0; k < 200000; ++k) {
    const Vec3 c(rng.uniform(-1, 1), rng.uniform(-1, 1), rng.uniform(-1, 1));
    const double r = std::pow(10.0, rng.uniform(-6, 0));
    // Origins from just outside to 1e6 radii away.
    const double dist = r * (1.0 + std::pow(10.0, rng.uniform(-3, 6)));
    const Vec3 o = c + dist * random_unit(rng);
    // Aim near the sphere so that about half the rays hit.
    const Vec3 target = c + 1.5 * r * rng.uniform() * random_unit(rng);
    const Vec3 d = (target - o).normalized();
    const double t = ray_sphere_entry(o, d, c, r);
    if (t == kNoHit) continue;
    ++hits;
    ASSERT_GT(t, 0.0);
    const Vec3 p = o + t * d;
    // Relative to the scale of the coordinates: a point near c cannot be stored closer than
    // eps |c| to the surface, whatever the algorithm.
    const double scale = std::max({r + dist, c.norm(), o.norm()});
    ASSERT_NEAR((p - c).norm(), r, 1e-12 * scale) << "sphere " << k;
    // An entry: the direction points into the sphere at the hit.
    ASSERT_LE(d.dot(p - c), 0.0);
  }
  EXPECT_GT(hits, 50000);
}

TEST(RaySphere, HitIsAccurateRelativeToRadiusForDistantOrigins) {
  // A ray from 1e4 radii away straight at the centre: the hit is one radius short of the centre.
  Rng rng(7);
  for (int k = 0; k < 10000; ++k) {
    const Vec3 c(rng.uniform(-1, 1), rng.uniform(-1, 1), rng.uniform(-1, 1));
    const double r = 1e-3;
    const Vec3 d = random_unit(rng);
    const double far = 1e4 * r;
    const double t = ray_sphere_entry(c - far * d, d, c, r);
    ASSERT_NEAR(t, far - r, 1e-12 * far);
    ASSERT_NEAR(((c - far * d + t * d) - c).norm(), r, 1e-12 * far);
  }
}

TEST(RaySphere, NoHitFromInside) {
  Rng rng(11);
  for (int k = 0; k < 100000; ++k) {
    const Vec3 c(rng.uniform(-1, 1), rng.uniform(-1, 1), rng.uniform(-1, 1));
    const double r = rng.uniform(0.01, 1);
    const Vec3 o = c + r * std::cbrt(rng.uniform(0, 0.999)) * random_unit(rng);
    ASSERT_EQ(ray_sphere_entry(o, random_unit(rng), c, r), kNoHit);
  }
}

TEST(RaySphere, NoHitWhenMovingAway) {
  const Vec3 c(0, 0, 0);
  EXPECT_EQ(ray_sphere_entry({2, 0, 0}, {1, 0, 0}, c, 1.0), kNoHit);
  EXPECT_EQ(ray_sphere_entry({2, 0.5, 0}, Vec3(1, 1, 0).normalized(), c, 1.0), kNoHit);
}

TEST(RaySphere, TangentAndNearTangentRays) {
  const Vec3 c(0, 0, 0);
  const double r = 1.0;
  const Vec3 d(1, 0, 0);
  // Exactly tangent: touches at (0, r, 0), t = 10.
  EXPECT_NEAR(ray_sphere_entry({-10, r, 0}, d, c, r), 10.0, 1e-12);
  // Just outside the silhouette: missed; just inside: hit with the chord entry point.
  EXPECT_EQ(ray_sphere_entry({-10, r * (1 + 1e-12), 0}, d, c, r), kNoHit);
  for (double eps : {1e-4, 1e-8, 1e-12}) {
    const double y = r * (1 - eps);
    const double t = ray_sphere_entry({-10, y, 0}, d, c, r);
    ASSERT_NE(t, kNoHit);
    const double expected = 10.0 - std::sqrt(r * r - y * y);
    EXPECT_NEAR(t, expected, 1e-12 * 10) << "eps = " << eps;
    EXPECT_NEAR(Vec3(-10 + t, y, 0).norm(), r, 1e-12);
  }
}
