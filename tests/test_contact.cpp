// Contact area (3.8)-(3.9), its degenerate rules, and the contact graph against brute force.
#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <numbers>
#include <tuple>

#include "geometry/contact.h"
#include "geometry/packing.h"
#include "geometry/random.h"

using namespace beampack;

namespace {

// (3.8)-(3.9) exactly as the paper writes them.
double paper_contact_area(double d, double ri, double rj) {
  const double li = 0.5 * (d - (rj * rj - ri * ri) / d);
  return std::numbers::pi * (ri * ri - li * li);
}

}  // namespace

TEST(ContactArea, EqualsPaperFormulaAndLensRadius) {
  Rng rng(3);
  for (int k = 0; k < 10000; ++k) {
    const double ri = rng.uniform(0.1, 1), rj = rng.uniform(0.1, 1);
    const double lo = std::abs(ri - rj), hi = ri + rj;
    const double d = rng.uniform(lo + 1e-3 * hi, hi);
    const ContactGeometry g = contact_geometry(d, ri, rj);
    ASSERT_NEAR(g.area, paper_contact_area(d, ri, rj), 1e-12 * ri * rj);
    // Closed-form lens radius of two intersecting spheres (circle of intersection):
    // a = sqrt(4 d^2 ri^2 - (d^2 - rj^2 + ri^2)^2) / (2 d).
    const double q = d * d - rj * rj + ri * ri;
    const double a = std::sqrt(4 * d * d * ri * ri - q * q) / (2 * d);
    ASSERT_NEAR(g.area, std::numbers::pi * a * a, 1e-12 * ri * rj);
    ASSERT_DOUBLE_EQ(g.distance, d);
  }
}

TEST(ContactArea, SymmetricInIAndJ) {
  Rng rng(5);
  for (int k = 0; k < 10000; ++k) {
    const double ri = rng.uniform(0.01, 1), rj = rng.uniform(0.01, 1);
    const double d = rng.uniform(0, ri + rj + 0.1);
    const ContactGeometry a = contact_geometry(d, ri, rj), b = contact_geometry(d, rj, ri);
    ASSERT_EQ(a.area, b.area);
    ASSERT_EQ(a.distance, b.distance);
  }
}

TEST(ContactArea, EqualSpheresHalfOverlapHasKnownArea) {
  // Equal spheres R at distance R: the lens radius is R sqrt(3)/2.
  EXPECT_NEAR(contact_geometry(1.0, 1.0, 1.0).area, std::numbers::pi * 0.75, 1e-15);
}

TEST(ContactArea, SeparatedAndTouchingSpheresHaveNoContact) {
  EXPECT_EQ(contact_geometry(2.0, 1.0, 1.0).area, 0.0);
  EXPECT_EQ(contact_geometry(2.5, 1.0, 1.0).area, 0.0);
  // Their distance is the real one, so a conductance K A / d is 0, not 0 / 0.
  EXPECT_EQ(contact_geometry(2.0, 1.0, 1.0).distance, 2.0);
  EXPECT_EQ(contact_geometry(2.5, 1.0, 1.0).distance, 2.5);
}

TEST(ContactArea, DegenerateCasesAreFiniteAndDocumented) {
  const double small = 0.3, large = 1.0;
  // Coincident centres: the smaller sphere's cross-section; distance floored.
  const ContactGeometry coincident = contact_geometry(0.0, small, large);
  EXPECT_DOUBLE_EQ(coincident.area, std::numbers::pi * small * small);
  EXPECT_DOUBLE_EQ(coincident.distance, kMinContactDistanceFraction * small);
  const ContactGeometry same = contact_geometry(0.0, 1.0, 1.0);
  EXPECT_DOUBLE_EQ(same.area, std::numbers::pi);
  EXPECT_GT(same.distance, 0.0);
  // One sphere strictly inside the other.
  const ContactGeometry nested = contact_geometry(0.5, small, large);
  EXPECT_DOUBLE_EQ(nested.area, std::numbers::pi * small * small);
  EXPECT_DOUBLE_EQ(nested.distance, 0.5);
  // Just outside internal tangency the lens (3.8) shrinks to a point; just inside, the nested rule
  // gives the full cross-section: the documented jump of MODEL.md's rule.
  const double d = large - small;
  const double lens = contact_geometry(d * (1 + 1e-9), small, large).area;
  EXPECT_NEAR(lens, paper_contact_area(d * (1 + 1e-9), small, large), 1e-12);
  EXPECT_LT(lens, 1e-8);
  EXPECT_DOUBLE_EQ(contact_geometry(d * (1 - 1e-9), small, large).area,
                   std::numbers::pi * small * small);
  // Tiny distances are floored, never divided by ~0.
  for (double dd : {1e-300, 1e-30, 1e-12}) {
    const ContactGeometry g = contact_geometry(dd, 1.0, 1.0);
    EXPECT_NEAR(g.area, std::numbers::pi, 1e-12);  // equal spheres almost coincident: full disc
    EXPECT_GE(g.distance, kMinContactDistanceFraction);
  }
}

namespace {

std::vector<std::tuple<std::uint32_t, std::uint32_t>> brute_force_pairs(const Particles& p) {
  std::vector<std::tuple<std::uint32_t, std::uint32_t>> pairs;
  for (std::uint32_t i = 0; i < p.size(); ++i)
    for (std::uint32_t j = i + 1; j < p.size(); ++j)
      if (p.alive[i] && p.alive[j] &&
          (p.centre[i] - p.centre[j]).norm() < p.radius[i] + p.radius[j])
        pairs.emplace_back(i, j);
  return pairs;
}

void expect_graph_equals_brute_force(const Particles& p) {
  const auto contacts = find_contacts(p);
  const auto expected = brute_force_pairs(p);
  ASSERT_EQ(contacts.size(), expected.size());
  for (std::size_t k = 0; k < contacts.size(); ++k) {
    ASSERT_EQ(std::make_tuple(contacts[k].i, contacts[k].j), expected[k]) << "pair " << k;
    const double d = (p.centre[contacts[k].i] - p.centre[contacts[k].j]).norm();
    const ContactGeometry g = contact_geometry(d, p.radius[contacts[k].i], p.radius[contacts[k].j]);
    ASSERT_EQ(contacts[k].area, g.area);
    ASSERT_EQ(contacts[k].distance, g.distance);  // the conduction distance of (3.2) too
  }
}

}  // namespace

TEST(ContactGraph, EqualsBruteForceOn5000RandomSpheres) {
  expect_graph_equals_brute_force(random_overlap_packing(5000, 1e-3, 0.325, 42));
}

TEST(ContactGraph, EqualsBruteForceWithMixedRadii) {
  Particles p;
  Rng rng(9);
  for (int k = 0; k < 5000; ++k)
    p.add({rng.uniform(0, 1), rng.uniform(0, 1), rng.uniform(0, 1)},
          std::pow(10.0, rng.uniform(-2.5, -1.3)));
  expect_graph_equals_brute_force(p);
}

TEST(ContactGraph, RecomputedAfterRemovalsDropsTheirPairs) {
  Particles p = random_overlap_packing(5000, 1e-3, 0.4, 43);
  Rng rng(1);
  for (int k = 0; k < 1000; ++k) p.remove(static_cast<std::size_t>(rng.uniform(0, 5000)));
  expect_graph_equals_brute_force(p);
  for (const Contact& c : find_contacts(p)) ASSERT_TRUE(p.alive[c.i] && p.alive[c.j]);
}

TEST(ContactGraph, DegenerateNeighboursGiveNoNaN) {
  Particles p;
  p.add({0, 0, 0}, 1.0);
  p.add({0, 0, 0}, 1.0);    // coincident
  p.add({0.1, 0, 0}, 0.2);  // inside the first two
  p.add({5, 5, 5}, 1.0);    // alone
  const auto contacts = find_contacts(p);
  ASSERT_EQ(contacts.size(), 3u);
  for (const Contact& c : contacts) {
    EXPECT_TRUE(std::isfinite(c.area) && c.area > 0);
    EXPECT_TRUE(std::isfinite(c.distance) && c.distance > 0);
  }
}

// Touching spheres of a close-packed (face-centred cubic) lattice: for many pairs d^2 rounds
// below (ri + rj)^2 while d rounds to ri + rj. The graph took those pairs with area 0 and distance
// 0, whose conductance K * 0 / 0 is NaN: a run of such a packing read from a file failed with
// a non-finite temperature. Every pair in the graph now overlaps by the distance itself.
TEST(ContactGraph, TouchingCloseLatticeHasOnlyOverlappingPairs) {
  for (double a : {1e-4, 1e-3 / 3.0, 5e-5, 1e-3 / 7.0}) {
    const double r = a / std::sqrt(2.0) / 2.0;  // nearest neighbours a / sqrt(2) apart: touching
    Particles p;
    for (int i = 0; i < 6; ++i)
      for (int j = 0; j < 6; ++j)
        for (int k = 0; k < 6; ++k) {
          const Vec3 corner(i * a, j * a, k * a);
          for (const Vec3& offset :
               {Vec3(0, 0, 0), Vec3(a / 2, a / 2, 0), Vec3(a / 2, 0, a / 2), Vec3(0, a / 2, a / 2)})
            p.add(corner + offset, r);
        }
    expect_graph_equals_brute_force(p);
    for (const Contact& c : find_contacts(p)) {
      ASSERT_GT(c.distance, 0.0) << "lattice constant " << a << ", pair " << c.i << "-" << c.j;
      ASSERT_GT(c.area, 0.0) << "lattice constant " << a << ", pair " << c.i << "-" << c.j;
    }
  }
}

// Spheres of 1e-17 m a kilometre apart: the box is 1e19 cells of their size wide, beyond a
// long; the cell count was cast from that double unclamped (undefined behaviour, which the
// sanitizer build reports). The grid must widen its cells and still find the touching pair.
TEST(ContactGraph, TinySpheresFarApartNeedNoMoreCellsThanALongHolds) {
  Particles p;
  p.add({0, 0, 0}, 1e-17);
  p.add({1.5e-17, 0, 0}, 1e-17);
  p.add({1e3, 2e3, 0}, 1e-17);
  p.add({1e3, 2e3, 3e3}, 1e-17);
  expect_graph_equals_brute_force(p);
  ASSERT_EQ(find_contacts(p).size(), 1u);
}

TEST(ContactGraph, EmptyAndSingleParticle) {
  EXPECT_TRUE(find_contacts(Particles{}).empty());
  Particles one;
  one.add({0, 0, 0}, 1.0);
  EXPECT_TRUE(find_contacts(one).empty());
}
