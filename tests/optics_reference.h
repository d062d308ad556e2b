#pragma once
// The optics tests' independent reference: one ray against every live sphere by brute force in
// double precision, and checks of the tracer against it ray by ray and for a whole beam.
#include <gtest/gtest.h>

#include <cmath>
#include <complex>
#include <cstdint>
#include <limits>
#include <span>
#include <utility>
#include <vector>

#include "engine/beam.h"
#include "engine/fresnel.h"
#include "engine/tracer.h"
#include "geometry/particles.h"
#include "geometry/ray_sphere.h"

namespace beampack::test {

// Embree device configurations the packet tests run under: the machine's own, and Embree capped
// at AVX2 and at SSE4.2, whose native packets hold 8 and 4 rays. There Embree splits the tracer's
// 16-ray packets, and a callback's lane is not the ray's slot in the packet.
inline constexpr const char* kEmbreeIsas[] = {"", "max_isa=avx2", "max_isa=sse4.2"};

// The reference: one ray against every live sphere in double precision, with the tracer's rules
// (MODEL.md section 3): nearest outside hit (ray_sphere_entry), ties to the lower particle id,
// the sphere just left skipped, (1 - R) E absorbed (R of the complex index when k > 0), specular
// reflection, cutoff (relative to the ray's initial energy; a ray left with 0 J ends) and bounce
// limit. It shares only fresnel.h's reflectance with the tracer.
struct ReferenceRay {
  std::vector<std::pair<std::uint32_t, double>> deposits;  // in hit order
  double escaped = 0.0, cutoff = 0.0;
};

// Fresnel reflectances for a real index n (mu = 1), written out apart from fresnel.h:
// n cos_t = sqrt(n^2 - sin^2 theta_i), r_s = (cos_i - n cos_t) / (cos_i + n cos_t),
// r_p = (n^2 cos_i - n cos_t) / (n^2 cos_i + n cos_t) (Born & Wolf 1.5 (21) with mu = 1).
struct HandFresnel {
  double par, perp;  // R_par = r_p^2, R_perp = r_s^2; unpolarised R = (par + perp) / 2
};
inline HandFresnel hand_fresnel(double cos_i, double n) {
  const double n_cos_t = std::sqrt(n * n - (1.0 - cos_i * cos_i));
  const double rs = (cos_i - n_cos_t) / (cos_i + n_cos_t);
  const double rp = (n * n * cos_i - n_cos_t) / (n * n * cos_i + n_cos_t);
  return {rp * rp, rs * rs};
}

// The nearest outside hit of the ray (o, d) on a live sphere other than `skip`, by brute force;
// ties to the lower particle id. particle == kNoParticle: none.
struct ReferenceHit {
  double t = kNoHit;
  std::uint32_t particle = kNoParticle;
};

inline ReferenceHit reference_nearest_hit(const Particles& p, const Vec3& o, const Vec3& d,
                                          std::uint32_t skip) {
  ReferenceHit best;
  for (std::uint32_t i = 0; i < p.size(); ++i) {
    if (!p.alive[i] || i == skip) continue;
    const double t = ray_sphere_entry(o, d, p.centre[i], p.radius[i]);
    if (t < best.t || (t == best.t && t < kNoHit && i < best.particle)) best = {t, i};
  }
  return best;
}

inline ReferenceRay reference_trace(const Particles& p, const OpticsSpec& spec, Vec3 o, Vec3 d,
                                    double e) {
  ReferenceRay out;
  const double e0 = e;
  std::uint32_t last = kNoParticle;
  for (int bounces = 0;;) {
    const ReferenceHit nearest = reference_nearest_hit(p, o, d, last);
    const double best = nearest.t;
    const std::uint32_t hit = nearest.particle;
    if (hit == kNoParticle) {
      out.escaped += e;
      return out;
    }
    const Vec3 point = o + best * d;
    const Vec3 normal = ((o + best * d - p.centre[hit]) / p.radius[hit]).normalized();
    const MaterialOptics& m = spec.materials[p.material[hit]];
    const std::complex<double> n = p.phase[hit] == Phase::solid ? m.n_solid : m.n_liquid;
    const double cos_i = -d.dot(normal);
    const double carried = (n.imag() == 0.0 ? reflectance(cos_i, n.real(), m.mu_hat)
                                            : reflectance(cos_i, n, m.mu_hat)) *
                           e;
    out.deposits.emplace_back(hit, e - carried);
    d = reflect(d, normal).normalized();
    o = point;
    e = carried;
    last = hit;
    if (carried == 0.0 || carried < spec.cutoff * e0 || ++bounces >= spec.max_bounces) {
      out.cutoff += carried;
      return out;
    }
  }
}

// A beam of given rays (origins on an entry plane, one direction, energy 1 J each unless given).
inline Beam custom_beam(const std::vector<Vec3>& origins, const Vec3& d) {
  Beam b;
  b.direction = d;
  b.centre = origins.front();
  b.origin = origins;
  b.intensity.assign(origins.size(), 1.0);
  b.ray_area = 1.0;
  b.power = static_cast<double>(origins.size());
  return b;
}

// Traces every ray alone through the tracer and through the reference; the hit counts, every
// particle's deposit and the escaped and cut-off energy must agree ray by ray: no missed hit, no
// phantom hit. Adds the number of hits to total_hits. Ray k carries energy_scale (1 + 1e-3 k) J
// (distinct energies; a scale far from 1 tells a relative cutoff from an absolute one). With
// `refs`, the reference rays (which the tracer's matched) are appended to it. Energies agree to
// `tolerance` times the ray's: round-off alone for a ray of one or two hits; a bounce multiplies
// a direction's rounding by ~2 l / (R cos theta_i) (free path l), so rays of several bounces,
// grazing ones most, need more (their hits are still the same, exactly).
inline void expect_rays_match_reference(const Particles& p, const OpticsSpec& spec,
                                        const std::vector<Vec3>& origins, const Vec3& d,
                                        std::uint64_t& total_hits,
                                        std::vector<ReferenceRay>* refs = nullptr,
                                        double energy_scale = 1.0, double tolerance = 1e-12) {
  Tracer tracer(p, spec);
  for (std::size_t k = 0; k < origins.size(); ++k) {
    const Beam beam = custom_beam({origins[k]}, d);
    const double energy = energy_scale * (1.0 + 1e-3 * static_cast<double>(k));
    const std::uint64_t hits_before = tracer.hits();
    const OpticsLedger before = tracer.ledger();
    tracer.launch(beam, std::span<const double>(&energy, 1));
    const RayState launched = tracer.save();  // the tracer's exact start point (upstream plane)
    const Vec3 start = launched.origin.back();
    std::vector<double> deposits;
    tracer.advance(std::numeric_limits<double>::infinity(), deposits);
    const ReferenceRay ref = reference_trace(p, spec, start, d, energy);
    const std::uint64_t hits = tracer.hits() - hits_before;
    total_hits += hits;
    ASSERT_EQ(hits, ref.deposits.size()) << "ray " << k << " from " << start.transpose();
    std::vector<double> expected(p.size(), 0.0);
    for (const auto& [i, e] : ref.deposits) expected[i] += e;
    deposits.resize(p.size(), 0.0);
    for (std::size_t i = 0; i < p.size(); ++i)
      ASSERT_NEAR(deposits[i], expected[i], tolerance * energy)
          << "ray " << k << ", particle " << i;
    EXPECT_NEAR(tracer.ledger().escaped - before.escaped, ref.escaped, tolerance * energy)
        << "ray " << k;
    EXPECT_NEAR(tracer.ledger().cutoff - before.cutoff, ref.cutoff, tolerance * energy)
        << "ray " << k;
    if (refs) refs->push_back(ref);
  }
  const OpticsLedger& l = tracer.ledger();
  EXPECT_NEAR(l.in_flight(), 0.0, 1e-12 * l.injected);
}

// The same rays launched together (16-ray packets, parallel chunks): per-particle deposits, the
// hit count and the escaped, cut-off and absorbed energy equal the reference's sums. With
// `reference_hits`, the reference's hit count is stored there.
inline void expect_beam_matches_reference(const Particles& p, const OpticsSpec& spec,
                                          const std::vector<Vec3>& origins, const Vec3& d,
                                          std::uint64_t* reference_hits = nullptr) {
  Tracer tracer(p, spec);
  std::vector<double> energies(origins.size());
  for (std::size_t k = 0; k < energies.size(); ++k)
    energies[k] = 1.0 + 1e-3 * static_cast<double>(k);
  tracer.launch(custom_beam(origins, d), energies);
  const RayState launched = tracer.save();
  std::vector<double> deposits;
  tracer.advance(std::numeric_limits<double>::infinity(), deposits);
  deposits.resize(p.size(), 0.0);
  std::vector<double> expected(p.size(), 0.0);
  std::uint64_t hits = 0;
  double escaped = 0, cutoff = 0, absorbed = 0;
  for (std::size_t k = 0; k < origins.size(); ++k) {
    const ReferenceRay ref = reference_trace(p, spec, launched.origin[k], d, energies[k]);
    hits += ref.deposits.size();
    escaped += ref.escaped;
    cutoff += ref.cutoff;
    for (const auto& [i, e] : ref.deposits) expected[i] += e, absorbed += e;
  }
  if (reference_hits) *reference_hits = hits;
  const OpticsLedger& l = tracer.ledger();
  EXPECT_EQ(tracer.hits(), hits);
  EXPECT_NEAR(l.escaped, escaped, 1e-12 * l.injected);
  EXPECT_NEAR(l.cutoff, cutoff, 1e-12 * l.injected);
  EXPECT_NEAR(l.absorbed, absorbed, 1e-12 * l.injected);
  for (std::size_t i = 0; i < p.size(); ++i) ASSERT_NEAR(deposits[i], expected[i], 1e-12) << i;
}

}  // namespace beampack::test
