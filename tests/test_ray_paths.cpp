// Recorded ray paths (rays_NNNN.vtp): per ray a chain of segments joined end to start, one per
// hit plus one for an escape, carrying the energy the ledger accounts for.
#include <gtest/gtest.h>

#include <limits>

#include "engine/tracer.h"
#include "geometry/packing.h"

using namespace beampack;

TEST(RayPaths, SegmentsChainAndCarryTheLedgersEnergy) {
  const Particles p = random_overlap_packing(2000, 1e-3, 0.325, 3);
  BeamSpec spec;
  spec.rays = 300;
  const Beam beam = make_beam(spec, 1e-3);
  Tracer tracer(p, OpticsSpec{});
  tracer.record_segments(true);
  tracer.launch(beam, 1e-13);
  std::vector<double> deposits;
  tracer.advance(std::numeric_limits<double>::infinity(), deposits);
  const std::vector<RaySegment> segments = tracer.take_segments();
  const OpticsLedger& l = tracer.ledger();
  std::size_t chains = 0;
  double first_energy = 0;
  for (std::size_t k = 0; k < segments.size(); ++k) {
    const bool new_ray = k == 0 || segments[k].from != segments[k - 1].to;
    if (new_ray) {
      ++chains;
      first_energy += segments[k].energy;
    } else {
      ASSERT_LE(segments[k].energy, segments[k - 1].energy) << k;  // reflection only loses energy
    }
    ASSERT_GT((segments[k].to - segments[k].from).norm(), 0.0) << k;
  }
  EXPECT_EQ(chains, beam.size());
  EXPECT_NEAR(first_energy, l.injected, 1e-12 * l.injected);  // each ray's first segment: E_k
  // A chain that escapes ends on the packing's box (where rays leave), carrying the escaped
  // energy; one cut off ends at its last hit, inside. One segment per hit, plus one per escape.
  const Box box = p.bounds();
  auto on_box = [&](const Vec3& x) {
    const double tol = 1e-12 * (box.upper - box.lower).maxCoeff();
    return ((x - box.lower).cwiseAbs().minCoeff() < tol) ||
           ((x - box.upper).cwiseAbs().minCoeff() < tol);
  };
  std::size_t escapes = 0;
  double escaped = 0;
  for (std::size_t k = 0; k < segments.size(); ++k) {
    const bool chain_ends = k + 1 == segments.size() || segments[k + 1].from != segments[k].to;
    if (chain_ends && on_box(segments[k].to)) ++escapes, escaped += segments[k].energy;
  }
  EXPECT_GT(escapes, 0u);
  EXPECT_LT(escapes, beam.size());  // and some rays were cut off
  EXPECT_EQ(segments.size(), tracer.hits() + escapes);
  EXPECT_NEAR(escaped, l.escaped, 1e-12 * l.injected);
  EXPECT_TRUE(tracer.take_segments().empty());  // handed over, store cleared
}
