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

// A sphere of radius 1e-6 to 1 near the origin and a ray from just outside it to 1e6 radii away,
// aimed at a point within `aim` radii of the centre. Each draw is its own statement, so the
// sequence does not depend on the compiler's order of evaluating operands.
struct SphereRay {
  Vec3 c;
  double r;
  double dist;  // of the origin from the centre
  Vec3 o, d;
};

SphereRay random_sphere_ray(Rng& rng, double aim) {
  SphereRay s;
  s.c = Vec3(rng.uniform(-1, 1), rng.uniform(-1, 1), rng.uniform(-1, 1));
  s.r = std::pow(10.0, rng.uniform(-6, 0));
  s.dist = s.r * (1.0 + std::pow(10.0, rng.uniform(-3, 6)));
  s.o = s.c + s.dist * random_unit(rng);
  const double offset = aim * s.r * rng.uniform();
  const Vec3 target = s.c + offset * random_unit(rng);
  s.d = (target - s.o).normalized();
  return s;
}

}  // namespace

TEST(RaySphere, HitPointLiesOnTheSphereForRandomRays) {
  Rng rng(20131023);
  int hits = 0;
  for (int k = 0; k < 200000; ++k) {
    // Aimed near the sphere so that about half the rays hit.
    const auto [c, r, dist, o, d] = random_sphere_ray(rng, 1.5);
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

// The hit normal (entry_normal, made unit by near_unit) is unit to round-off and points from the
// centre to the hit point, for radii from 1e-6 to 1 and origins up to 1e6 radii away.
TEST(RaySphere, EntryNormalIsUnitAndRadial) {
  Rng rng(1729);
  int hits = 0;
  for (int k = 0; k < 100000; ++k) {
    const auto [c, r, dist, o, d] = random_sphere_ray(rng, 1.2);
    const double t = ray_sphere_entry(o, d, c, r);
    if (t == kNoHit) continue;
    ++hits;
    const Vec3 n = near_unit(entry_normal(o, d, t, c, r));
    ASSERT_NEAR(n.norm(), 1.0, 4e-16) << k;
    const Vec3 exact = (o + t * d - c).normalized();
    // As accurate as the hit point itself: its round-off relative to r (see the test above).
    const double scale = std::max({o.cwiseAbs().maxCoeff(), c.cwiseAbs().maxCoeff(), r});
    ASSERT_LT((n - exact).norm(), 1e-15 + 64e-16 * scale / r) << k;
    ASSERT_LT(n.dot(d), 0.0) << k;  // an outside hit: the normal faces the ray
  }
  EXPECT_GT(hits, 30000);
}

// near_unit: one Newton step for vectors already near unit length, the division otherwise; both
// give |v| = 1 to round-off and keep the direction.
TEST(RaySphere, NearUnitNormalisesNearAndFarFromUnitLength) {
  Rng rng(99);
  for (int k = 0; k < 20000; ++k) {
    const Vec3 u = random_unit(rng);
    for (double length : {1.0, 1.0 + 1e-12, 1.0 - 3e-9, 1.0 + 2e-8, 0.5, 7.0, 1e-9, 1e12}) {
      const Vec3 n = near_unit(length * u);
      ASSERT_NEAR(n.norm(), 1.0, 4e-16) << length;
      ASSERT_LT((n - u).norm(), 1e-15) << length;
    }
  }
}

// On the surface counts as inside (MODEL.md section 3: hits are entered from outside): a ray whose
// origin lies exactly on a sphere is leaving it whichever way it points, and has no hit there at
// t = 0, however far into the sphere it aims. Integer coordinates put the origins exactly on it.
TEST(RaySphere, NoHitFromAnOriginExactlyOnTheSurface) {
  const Vec3 c(1, -2, 3);
  const double r = 5.0;
  for (const Vec3& offset : {Vec3(5, 0, 0), Vec3(0, -5, 0), Vec3(3, 4, 0), Vec3(0, -3, -4)}) {
    const Vec3 o = c + offset;
    ASSERT_EQ((o - c).squaredNorm(), r * r);
    const Vec3 inward = -offset / r;
    for (const Vec3& d : {inward, Vec3((inward + Vec3(0.1, 0.2, -0.1)).normalized())})
      EXPECT_EQ(ray_sphere_entry(o, d, c, r), kNoHit)
          << offset.transpose() << " along " << d.transpose();
  }
}
