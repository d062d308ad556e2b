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
  // One segment per hit, plus one per ray that escapes (a cut-off ray ends at its last hit).
  EXPECT_GE(segments.size(), tracer.hits());
  EXPECT_LE(segments.size(), tracer.hits() + beam.size());
  EXPECT_GT(l.escaped, 0.0);
  EXPECT_GT(segments.size(), tracer.hits());
  EXPECT_TRUE(tracer.take_segments().empty());  // handed over, store cleared
}
