// The grid walk for bounced rays: interleaved walks (intersect_many) give each ray exactly the
// answer of its own walk (intersect1), and both the brute-force nearest outside hit; rays that
// hit nothing leave the query untouched.
// Seeded property tests on random-overlap packings with removed spheres.
#include <gtest/gtest.h>

#include <algorithm>
#include <bit>
#include <cstdint>
#include <limits>
#include <numeric>
#include <span>
#include <utility>
#include <vector>

#include "engine/sphere_grid.h"
#include "geometry/packing.h"
#include "geometry/random.h"
#include "geometry/ray_sphere.h"

namespace beampack {
namespace {

constexpr double kD = 1e-3;

bool same_bits(double a, double b) {
  return std::bit_cast<std::uint64_t>(a) == std::bit_cast<std::uint64_t>(b);
}

Vec3 random_unit(Rng& rng) {
  for (;;) {
    const Vec3 u(rng.uniform(-1, 1), rng.uniform(-1, 1), rng.uniform(-1, 1));
    if (u.squaredNorm() > 1e-6 && u.squaredNorm() <= 1.0) return u.normalized();
  }
}

// Directions of three kinds: generic, in a coordinate plane (one zero component) and along an
// axis (two zeros), since the walk treats a zero component apart (no steps, a slab test).
Vec3 random_direction(Rng& rng) {
  Vec3 d = random_unit(rng);
  const auto kind = rng.next() % 4;
  if (kind == 0) {
    const auto a = rng.next() % 3;
    d = Vec3::Zero();
    d[a] = rng.next() % 2 ? 1.0 : -1.0;
  } else if (kind == 1) {
    d[rng.next() % 3] = 0.0;
    d.normalize();
  }
  return d;
}

// Rays as the tracer makes them (leaving a sphere's surface, that sphere skipped) and anywhere
// inside or around the box, half of them limited to a finite t_hit.
struct Rays {
  std::vector<Vec3> origin, direction;
  std::vector<std::uint32_t> skip;
  std::vector<double> t_limit;  // initial t_hit
};

Rays mixed_rays(const Particles& p, std::size_t count, std::uint64_t seed) {
  Rng rng(seed);
  Rays rays;
  for (std::size_t r = 0; r < count; ++r) {
    std::uint32_t skip = kNoParticle;
    Vec3 o;
    if (r % 3 == 0) {
      skip = static_cast<std::uint32_t>(rng.next() % p.size());
      o = p.centre[skip] + p.radius[skip] * random_unit(rng);
    } else if (r % 3 == 1) {
      o = Vec3(rng.uniform(), rng.uniform(), rng.uniform()) * kD;
    } else {
      o = Vec3(rng.uniform(-0.5, 1.5), rng.uniform(-0.5, 1.5), rng.uniform(-0.5, 1.5)) * kD;
    }
    rays.origin.push_back(o);
    rays.direction.push_back(random_direction(rng));
    rays.skip.push_back(skip);
    rays.t_limit.push_back(r % 2 ? rng.uniform(0.0, 0.3 * kD) : kNoHit);
  }
  return rays;
}

struct Answers {
  std::vector<double> t;
  std::vector<std::uint32_t> particle;
  std::vector<Vec3> normal;
  explicit Answers(const Rays& rays)
      : t(rays.t_limit),
        particle(rays.t_limit.size(), kNoParticle),
        normal(rays.t_limit.size(), Vec3::Constant(-7.0)) {}
  RayQuery query(const Rays& rays) {
    return {rays.origin.data(), rays.direction.data(), rays.skip.data(),
            t.data(),           particle.data(),       normal.data()};
  }
};

// The contract spelled out: the nearest outside hit before the initial t_hit over every sphere
// still there, the skipped one excepted, ties (also with the initial t_hit) to the lower id.
Answers brute_force(const Particles& p, const std::vector<std::uint8_t>& gone, const Rays& rays) {
  Answers a(rays);
  for (std::size_t r = 0; r < rays.origin.size(); ++r)
    for (std::uint32_t i = 0; i < p.size(); ++i) {
      if (i == rays.skip[r] || gone[i]) continue;
      const double t =
          ray_sphere_entry(rays.origin[r], rays.direction[r], p.centre[i], p.radius[i]);
      if (t == kNoHit) continue;
      if (t < a.t[r] || (t == a.t[r] && i < a.particle[r])) a.t[r] = t, a.particle[r] = i;
    }
  return a;
}

Answers single_walks(const SphereGrid& grid, const Rays& rays) {
  Answers a(rays);
  const RayQuery q = a.query(rays);
  for (std::uint32_t r = 0; r < rays.origin.size(); ++r) grid.intersect1(q, r);
  return a;
}

// All rays, in a shuffled order, handed over in batches of batch_size.
Answers batched_walks(const SphereGrid& grid, const Rays& rays, std::size_t batch_size,
                      std::uint64_t seed) {
  std::vector<std::uint32_t> ids(rays.origin.size());
  std::iota(ids.begin(), ids.end(), 0u);
  Rng rng(seed);
  for (std::size_t k = ids.size(); k > 1; --k) std::swap(ids[k - 1], ids[rng.next() % k]);
  Answers a(rays);
  const RayQuery q = a.query(rays);
  for (std::size_t k = 0; k < ids.size(); k += batch_size)
    grid.intersect_many(q, std::span(ids).subspan(k, std::min(batch_size, ids.size() - k)));
  return a;
}

TEST(SphereGrid, BatchedWalksEqualSingleWalksAndBruteForce) {
  for (std::size_t n : {200u, 5000u}) {
    const Particles p = random_overlap_packing(n, kD, 0.325, 40 + n);
    const Rays rays = mixed_rays(p, 3000, 41 + n);
    std::vector<std::uint8_t> gone(n, 0);
    std::vector<std::uint32_t> victims;
    for (std::uint32_t i = 3; i < n; i += 9) victims.push_back(i), gone[i] = 1;
    const Answers truth = brute_force(p, gone, rays);
    // Both outcomes well represented, or the comparisons below would prove little.
    const auto hits = std::count_if(truth.particle.begin(), truth.particle.end(),
                                    [](std::uint32_t i) { return i != kNoParticle; });
    EXPECT_GT(hits, 300) << n;
    EXPECT_LT(hits, 2400) << n;
    for (double cell_factor : {0.7, 3.0}) {
      SphereGrid grid(p, cell_factor);
      grid.remove(victims);
      const Answers single = single_walks(grid, rays);
      SCOPED_TRACE(::testing::Message() << "n " << n << " cell factor " << cell_factor);
      for (std::size_t r = 0; r < rays.origin.size(); ++r) {
        ASSERT_EQ(single.particle[r], truth.particle[r]) << "ray " << r;
        ASSERT_TRUE(same_bits(single.t[r], truth.t[r])) << "ray " << r;
      }
      for (std::size_t batch : {1u, 3u, 17u, 1000u}) {
        const Answers many = batched_walks(grid, rays, batch, batch + n);
        for (std::size_t r = 0; r < rays.origin.size(); ++r) {
          ASSERT_EQ(many.particle[r], single.particle[r]) << "batch " << batch << " ray " << r;
          ASSERT_TRUE(same_bits(many.t[r], single.t[r])) << "batch " << batch << " ray " << r;
          for (int a = 0; a < 3; ++a)
            ASSERT_TRUE(same_bits(many.normal[r][a], single.normal[r][a]))
                << "batch " << batch << " ray " << r << " axis " << a;
        }
      }
    }
  }
}

// Rays that hit nothing: leaving the box, outside the box's slab along an axis they do not
// move on, or stopped by a t_hit shorter than any gap. Their t_hit, particle and normal stay.
TEST(SphereGrid, RaysThatHitNothingLeaveTheQueryUntouched) {
  const Particles p = random_overlap_packing(5000, kD, 0.325, 60);
  SphereGrid grid(p);
  Rng rng(61);
  Rays rays;
  auto add = [&](Vec3 o, Vec3 d, double t_limit) {
    rays.origin.push_back(o), rays.direction.push_back(d);
    rays.skip.push_back(kNoParticle), rays.t_limit.push_back(t_limit);
  };
  for (int k = 0; k < 300; ++k) {
    const Vec3 outside = Vec3(rng.uniform(1.5, 2.0), rng.uniform(), rng.uniform()) * kD;
    Vec3 away = random_unit(rng);
    away.x() = std::abs(away.x());
    add(outside, away, k % 2 ? kNoHit : kD);
    add(outside, Vec3(0, k % 2 ? 1 : -1, 0), kNoHit);  // slab x excludes the box
    add(Vec3(rng.uniform(), rng.uniform(), rng.uniform()) * kD, random_direction(rng), 1e-9 * kD);
  }
  const Answers none = brute_force(p, std::vector<std::uint8_t>(p.size(), 0), rays);
  for (std::size_t r = 0; r < rays.origin.size(); ++r)
    ASSERT_EQ(none.particle[r], kNoParticle) << "ray " << r << " is no miss";
  std::vector<std::uint32_t> ids(rays.origin.size());
  std::iota(ids.begin(), ids.end(), 0u);
  Answers a(rays);
  for (std::uint32_t& i : a.particle) i = 4321;  // any value: it must survive
  grid.intersect_many(a.query(rays), ids);
  for (std::size_t r = 0; r < rays.origin.size(); ++r) {
    ASSERT_EQ(a.particle[r], 4321u) << "ray " << r;
    ASSERT_TRUE(same_bits(a.t[r], rays.t_limit[r])) << "ray " << r;
    ASSERT_EQ(a.normal[r], Vec3(Vec3::Constant(-7.0))) << "ray " << r;
  }
}

// Ties in t (spheres sharing a centre and radius, as in the coincident-centre packings a run
// accepts) go to the lower particle id, as in the Embree scene: which copy absorbs must not
// depend on the search. Every fifth sphere gets a copy with a higher id.
TEST(SphereGrid, TiesInDistanceGoToTheLowerParticleId) {
  Particles p = random_overlap_packing(1000, kD, 0.325, 70);
  const std::size_t n = p.size();
  std::vector<std::uint32_t> copy_of(n, kNoParticle);
  for (std::uint32_t i = 0; i < n; i += 5)
    copy_of[i] = static_cast<std::uint32_t>(p.add(p.centre[i], p.radius[i]));
  const Rays rays = mixed_rays(p, 3000, 71);
  const Answers truth = brute_force(p, std::vector<std::uint8_t>(p.size(), 0), rays);
  std::size_t ties = 0;
  for (std::size_t r = 0; r < rays.origin.size(); ++r) {
    const std::uint32_t i = truth.particle[r];
    // A ray leaving one of a pair starts on its copy too: only free rays say who wins a tie.
    if (rays.skip[r] != kNoParticle || i == kNoParticle) continue;
    ASSERT_LT(i, n) << "ray " << r << ": the copy won the tie";
    ties += copy_of[i] != kNoParticle;
  }
  EXPECT_GT(ties, 100u);  // enough tied hits for the comparison below to mean something
  for (double cell_factor : {0.7, 3.0}) {
    const SphereGrid grid(p, cell_factor);
    const Answers single = single_walks(grid, rays);
    const Answers many = batched_walks(grid, rays, 17, 72);
    for (std::size_t r = 0; r < rays.origin.size(); ++r) {
      ASSERT_EQ(single.particle[r], truth.particle[r])
          << "cell factor " << cell_factor << " ray " << r;
      ASSERT_EQ(many.particle[r], truth.particle[r])
          << "cell factor " << cell_factor << " ray " << r;
    }
  }
}

}  // namespace
}  // namespace beampack
