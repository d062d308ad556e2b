// Tracer properties on packings: the ledger closes, deposits are bit-identical across threads and
// packet/single-ray paths, removal is immediate, and a pulse traced in budgeted chunks equals the
// whole pulse.
#include <gtest/gtest.h>
#include <tbb/global_control.h>
#include <tbb/task_arena.h>

#include <algorithm>
#include <array>
#include <cmath>
#include <cstdlib>
#include <limits>
#include <memory>
#include <numbers>
#include <numeric>

#include "engine/beam.h"
#include "engine/float_mode.h"
#include "engine/state_io.h"
#include "engine/tracer.h"
#include "geometry/packing.h"
#include "geometry/ray_sphere.h"
#include "tests/expect_error.h"
#include "tests/long_tests.h"
#include "tests/optics_reference.h"

namespace beampack {
namespace {

using test::ReferenceRay;

constexpr double kAll = std::numeric_limits<double>::infinity();
constexpr double kD = 1e-3;

struct Traced {
  std::vector<double> deposits;
  OpticsLedger ledger;
  std::uint64_t primary = 0, bounced = 0, hits = 0;
};

OpticsSpec optics_for(double n_hat, bool packets = true,
                      SceneUpdate update = OpticsSpec{}.scene_update,
                      BounceSearch bounce = OpticsSpec{}.bounce_search,
                      std::size_t chunk_rays = 256) {
  OpticsSpec spec;
  spec.chunk_rays = chunk_rays;
  spec.materials[0].n_solid = n_hat;
  spec.packets = packets;
  spec.bounce_search = bounce;
  spec.scene_update = update;
  return spec;
}

Traced trace(const Particles& p, const OpticsSpec& spec, const BeamSpec& beam_spec,
             double budget = kAll) {
  Tracer tracer(p, spec);
  tracer.launch(make_beam(beam_spec, kD), 1e-9);
  Traced run;
  while (tracer.advance(budget, run.deposits) > 0) {
  }
  run.ledger = tracer.ledger();
  run.primary = tracer.primary_segments();
  run.bounced = tracer.bounced_segments();
  run.hits = tracer.hits();
  return run;
}

const Particles& packing_1e4() {
  static const Particles p = random_overlap_packing(10000, kD, 0.325, 3);
  return p;
}

TEST(OpticsTracer, LedgerClosesOnA1e4Packing) {
  for (double n_hat : {1.4, 20.0}) {
    const Traced run = trace(packing_1e4(), optics_for(n_hat), BeamSpec{});
    const OpticsLedger& l = run.ledger;
    EXPECT_NEAR(l.absorbed + l.escaped + l.cutoff, l.injected, 1e-12 * l.injected) << n_hat;
    const double deposited = std::accumulate(run.deposits.begin(), run.deposits.end(), 0.0);
    EXPECT_NEAR(deposited, l.absorbed, 1e-12 * l.injected);
    EXPECT_EQ(run.primary, 1000u);
    EXPECT_GT(run.bounced, 0u);
    EXPECT_GT(l.absorbed, 0.1 * l.injected);
    EXPECT_GT(l.escaped, 0.0);
    if (n_hat == 20.0) {
      EXPECT_GT(run.hits, 3 * run.primary);  // highly reflective: many bounces
    }
  }
}

// A flat beam's rays carry equal energies: summed one by one onto a running total, their rounding
// errors all lean one way (a million rays: injected 3e-11 short of P tau a pulse, 1e-9 after a
// hundred pulses). The ledger's sums keep the bits each addition loses: the injected energy is
// the pulses' P tau to round-off, however many rays, and the ledger closes as tightly.
TEST(OpticsTracer, InjectedEnergyIsThePulsesPowerTimesDurationForAMillionEqualRays) {
  BeamSpec flat;
  flat.profile = "flat";
  flat.sampling = "stratified";
  flat.rays = 1'000'000;
  OpticsSpec spec = optics_for(1.4);
  spec.max_bounces = 1;  // first hits only: the sums, not the tracing, are under test
  const Particles p = random_overlap_packing(200, kD, 0.325, 3);
  Tracer tracer(p, spec);
  const Beam beam = make_beam(flat, kD);
  const double tau = 3e-13;
  std::vector<double> deposits;
  constexpr int kPulses = 4;
  for (int k = 0; k < kPulses; ++k) {
    tracer.launch(beam, tau);
    while (tracer.advance(kAll, deposits) > 0) {
    }
  }
  const OpticsLedger& l = tracer.ledger();
  const double expected = kPulses * flat.power * tau;
  EXPECT_NEAR(l.injected, expected, 1e-14 * expected);
  EXPECT_GT(l.absorbed, 0.01 * expected);
  EXPECT_NEAR(l.absorbed + l.escaped + l.cutoff, l.injected, 1e-14 * expected);
}

TEST(OpticsTracer, CutoffAndBounceLimitEndRaysIntoTheCutoffBin) {
  OpticsSpec spec = optics_for(20.0);
  spec.max_bounces = 2;
  const Traced run = trace(packing_1e4(), spec, BeamSpec{});
  EXPECT_GT(run.ledger.cutoff, 0.0);
  EXPECT_LE(run.hits, 2u * 1000u);
  // From below too: a second hit is made (a limit that ended every ray at its first passes the
  // bounds above), and ray by ray as the reference's own bounce count has it.
  spec.max_bounces = 1;
  const Traced once = trace(packing_1e4(), spec, BeamSpec{});
  EXPECT_LE(once.hits, 1000u);
  EXPECT_GT(run.hits, once.hits + 100u);
  spec.max_bounces = 2;
  {
    const Beam beam = make_beam(BeamSpec{}, kD);
    std::uint64_t hits = 0;
    test::expect_rays_match_reference(packing_1e4(), spec, beam.origin, beam.direction, hits,
                                      nullptr, 1e-9, 1e-9);
    EXPECT_EQ(hits, run.hits);
  }
  EXPECT_NEAR(run.ledger.absorbed + run.ledger.escaped + run.ledger.cutoff, run.ledger.injected,
              1e-12 * run.ledger.injected);
  spec = optics_for(20.0);
  spec.cutoff = 0.5;  // a ray ends once it carries less than half its initial energy
  const Traced cut = trace(packing_1e4(), spec, BeamSpec{});
  EXPECT_GT(cut.ledger.cutoff, 0.0);
  // Ray by ray against the double reference (its own relative-cutoff rule), with energies of a
  // real pulse's rays (~1e-9 J): a cutoff taken as absolute (0.5 J) would end every ray at its
  // first hit. Energies to 1e-9 of the ray's: several bounces amplify round-off (see the helper).
  const Beam beam = make_beam(BeamSpec{}, kD);
  std::vector<ReferenceRay> refs;
  std::uint64_t hits = 0;
  test::expect_rays_match_reference(packing_1e4(), spec, beam.origin, beam.direction, hits, &refs,
                                    1e-9, 1e-9);
  ASSERT_EQ(refs.size(), beam.size());
  // What the rule implies, by hand. (The former comment held R_F >= R_F(normal) at n = 20, so
  // that every cut ray had >= 4 hits; it is the other way round: unpolarised R_F falls from
  // (19/21)^2 = 0.819 at normal incidence to 0.495 near Brewster's angle, atan 20 = 87.1 deg,
  // before rising to 1 at grazing, so one near-Brewster hit ends a ray.) Bounds that do hold:
  // R_F = (R_par + R_perp) / 2 >= R_perp / 2 >= R_perp(normal) / 2 = 0.409 (R_perp grows with
  // the angle). A ray is cut at its first hit that leaves it below e / 2, so it carries at least
  // e / 2 into that hit and leaves with [0.409 e / 2, e / 2); a ray never cut escapes with at
  // least e / 2.
  const double r_least = 0.5 * (19.0 / 21.0) * (19.0 / 21.0);
  std::size_t cut_rays = 0, cut_after_four = 0, escaped_after_hits = 0;
  for (std::size_t k = 0; k < refs.size(); ++k) {
    const double e0 = 1e-9 * (1.0 + 1e-3 * static_cast<double>(k));
    const ReferenceRay& ref = refs[k];
    if (ref.cutoff == 0.0) {
      EXPECT_GE(ref.escaped, 0.5 * e0) << "ray " << k;
      escaped_after_hits += !ref.deposits.empty();
      continue;
    }
    ++cut_rays;
    cut_after_four += ref.deposits.size() >= 4;
    EXPECT_LT(ref.cutoff, 0.5 * e0) << "ray " << k;
    EXPECT_GE(ref.cutoff, r_least * 0.5 * e0) << "ray " << k;
    EXPECT_GE(ref.cutoff + ref.deposits.back().second, 0.5 * e0) << "ray " << k;
  }
  // At most angles R_F is near 0.8 (0.819^3 = 0.549 > 1/2): many rays need four hits or more.
  EXPECT_GT(cut_rays, 100u);
  EXPECT_GT(cut_after_four, 10u);
  EXPECT_GT(escaped_after_hits, 10u);
}

// Every bounce on a packing obeys the optics of one hit, checked on the tracer's own recorded
// path (its segments), so that the test holds however many bounces a ray makes: in a packing a
// path is chaotic (each bounce multiplies a direction's rounding by ~2 l / R), so after ~10
// bounces two correct traces in double part ways and a whole-path reference cannot follow.
// Per segment, independently of the tracer: the brute-force nearest outside hit from its start
// along its direction is where it ends (the sphere just left skipped), the next segment leaves
// along the specular reflection d - 2 (d.n) n, it carries R_F(cos_i) times the energy (Fresnel by
// hand), the sphere keeps (1 - R_F) of it; the last segment escapes or its hit falls below the
// cutoff. Deposits and the ledger's bins must equal these sums: the ledger's closing (absorbed =
// E - carried in the tracer) says nothing of whether the carried energy was right.
TEST(OpticsTracer, EveryBounceOnAPackingObeysTheOpticsOfOneHit) {
  const Particles p = random_overlap_packing(300, kD, 0.5, 5);
  const double n_hat = 20.0;
  const OpticsSpec spec = optics_for(n_hat);
  const Beam beam = make_beam(BeamSpec{}, kD);
  Tracer tracer(p, spec);
  tracer.record_segments(true);
  std::vector<double> deposits, expected(p.size(), 0.0);
  double escaped = 0, cutoff = 0, injected = 0;
  std::uint64_t hits = 0;
  std::size_t longest = 0;
  for (std::size_t k = 0; k < beam.size(); ++k) {
    const double e0 = 1e-9 * (1.0 + 1e-3 * static_cast<double>(k));
    injected += e0;
    tracer.launch(test::custom_beam({beam.origin[k]}, beam.direction),
                  std::span<const double>(&e0, 1));
    tracer.advance(kAll, deposits);
    const std::vector<RaySegment> segs = tracer.take_segments();
    ASSERT_FALSE(segs.empty()) << "ray " << k;
    longest = std::max(longest, segs.size());
    std::uint32_t last = kNoParticle;
    double e = e0;
    Vec3 d = beam.direction;
    for (std::size_t j = 0; j < segs.size(); ++j) {
      const RaySegment& sg = segs[j];
      SCOPED_TRACE(::testing::Message() << "ray " << k << ", segment " << j);
      ASSERT_NEAR(sg.energy, e, 1e-9 * e0);
      if (j > 0) {
        ASSERT_EQ(sg.from, segs[j - 1].to);
        const Vec3 along = (sg.to - sg.from).normalized();
        ASSERT_LT((along - d).norm(), 1e-9);  // d: the specular reflection, below
        d = along;
      }
      const test::ReferenceHit hit = test::reference_nearest_hit(p, sg.from, d, last);
      if (hit.particle == kNoParticle) {
        ASSERT_EQ(j + 1, segs.size());  // no sphere ahead: it escaped
        escaped += e;
        break;
      }
      ASSERT_NEAR((sg.to - sg.from).norm(), hit.t, 1e-9 * p.radius[hit.particle]);
      const Vec3 normal = (sg.to - p.centre[hit.particle]).normalized();
      const test::HandFresnel f = test::hand_fresnel(-d.dot(normal), n_hat);
      const double r = 0.5 * (f.par + f.perp);
      expected[hit.particle] += (1.0 - r) * e;
      ++hits;
      e *= r;
      last = hit.particle;
      d = d - 2.0 * d.dot(normal) * normal;
      if (j + 1 == segs.size()) {  // it ended at this hit
        EXPECT_TRUE(e < spec.cutoff * e0 || j + 1 >= static_cast<std::size_t>(spec.max_bounces));
        cutoff += e;
      }
    }
  }
  deposits.resize(p.size(), 0.0);
  for (std::size_t i = 0; i < p.size(); ++i)
    ASSERT_NEAR(deposits[i], expected[i], 1e-9 * injected) << i;
  const OpticsLedger& l = tracer.ledger();
  EXPECT_EQ(tracer.hits(), hits);
  EXPECT_NEAR(l.injected, injected, 1e-12 * injected);
  EXPECT_NEAR(l.escaped, escaped, 1e-9 * injected);
  EXPECT_NEAR(l.cutoff, cutoff, 1e-9 * injected);
  EXPECT_GT(hits, 4u * beam.size());  // a multi-bounce scene: ~5 hits a ray, some 40
  EXPECT_GT(longest, 20u);
}

// Packets or single rays for primaries, Embree or the grid for bounces: the same hits in double,
// hence bit-identical deposits.
// Under each Embree ISA (packets split into 8- or 4-ray ones below AVX-512) as well.
TEST(OpticsTracer, PacketsAndSingleRaysGiveIdenticalDeposits) {
  const SceneUpdate update = OpticsSpec{}.scene_update;
  for (double n_hat : {1.4, 20.0}) {
    const Traced a =
        trace(packing_1e4(), optics_for(n_hat, true, update, BounceSearch::embree), BeamSpec{});
    const Traced b =
        trace(packing_1e4(), optics_for(n_hat, false, update, BounceSearch::embree), BeamSpec{});
    // Interleaved grid walks (after packets, or after single-ray primaries in the same waves),
    // incoherent packets.
    const std::pair<BounceSearch, bool> variants[] = {
        {BounceSearch::grid, true}, {BounceSearch::grid, false}, {BounceSearch::packets, true}};
    for (const char* isa : test::kEmbreeIsas) {
      for (const auto& [bounce, packets] : variants) {
        SCOPED_TRACE(std::string(isa) + (packets ? " packets" : " single rays"));
        OpticsSpec spec = optics_for(n_hat, packets, update, bounce);
        spec.embree_config = isa;
        const Traced c = trace(packing_1e4(), spec, BeamSpec{});
        EXPECT_EQ(a.deposits, c.deposits);
        EXPECT_EQ(a.ledger.absorbed, c.ledger.absorbed);
        EXPECT_EQ(a.ledger.escaped, c.ledger.escaped);
        EXPECT_EQ(a.ledger.cutoff, c.ledger.cutoff);
        EXPECT_EQ(a.hits, c.hits);
      }
    }
    EXPECT_EQ(a.deposits, b.deposits);
    EXPECT_EQ(a.ledger.absorbed, b.ledger.absorbed);
    EXPECT_EQ(a.hits, b.hits);
  }
}

// With 2 * 10^4 rays the pipeline's items hold more chunks than kBatchRays rays, and how many
// depends on the threads allowed: 4 chunks of 256 rays with one, 1 with eight (an arena of
// eight, so the items differ whatever cores the machine has).
TEST(OpticsTracer, OneAndTwoThreadsGiveBitIdenticalDeposits) {
  for (std::size_t rays : {3000, 20000}) {
    BeamSpec beam;
    beam.rays = rays;
    Traced one, two, eight;
    {
      tbb::global_control limit(tbb::global_control::max_allowed_parallelism, 1);
      one = trace(packing_1e4(), optics_for(20.0), beam);
    }
    {
      tbb::global_control limit(tbb::global_control::max_allowed_parallelism, 2);
      two = trace(packing_1e4(), optics_for(20.0), beam);
    }
    {
      tbb::global_control limit(tbb::global_control::max_allowed_parallelism, 8);
      tbb::task_arena(8).execute([&] { eight = trace(packing_1e4(), optics_for(20.0), beam); });
    }
    for (const Traced* other : {&two, &eight}) {
      EXPECT_EQ(one.deposits, other->deposits) << rays;
      EXPECT_EQ(one.ledger.absorbed, other->ledger.absorbed) << rays;
      EXPECT_EQ(one.ledger.escaped, other->ledger.escaped) << rays;
      EXPECT_EQ(one.ledger.cutoff, other->ledger.cutoff) << rays;
    }
  }
}

// The path is identical; only the order of the per-particle sums differs (call by call instead
// of ray by ray), hence equality to round-off and identical event counts.
TEST(OpticsTracer, BudgetedChunksEqualTheWholePulse) {
  const Traced whole = trace(packing_1e4(), optics_for(1.4), BeamSpec{});
  for (double budget : {1e-4, 3.3e-5}) {
    const Traced chunks = trace(packing_1e4(), optics_for(1.4), BeamSpec{}, budget);
    EXPECT_EQ(chunks.hits, whole.hits);
    EXPECT_EQ(chunks.primary + chunks.bounced, whole.primary + whole.bounced);
    ASSERT_EQ(chunks.deposits.size(), whole.deposits.size());
    for (std::size_t i = 0; i < whole.deposits.size(); ++i)
      ASSERT_NEAR(chunks.deposits[i], whole.deposits[i], 1e-13 * whole.ledger.injected) << i;
    EXPECT_NEAR(chunks.ledger.escaped, whole.ledger.escaped, 1e-13 * whole.ledger.injected);
  }
}

// The list of deposited particles (what the simulation clears, sums and hands to the heat step)
// names each particle with a deposit exactly once, call by call, in budgeted steps.
TEST(OpticsTracer, TheDepositedListNamesEveryParticleWithADepositOnce) {
  Tracer tracer(packing_1e4(), optics_for(20.0));
  tracer.launch(make_beam(BeamSpec{}, kD), 1e-9);
  std::vector<double> deposits;
  std::size_t steps = 0, listed = 0;
  for (bool live = true; live; ++steps) {
    std::vector<std::uint32_t> deposited;
    std::fill(deposits.begin(), deposits.end(), 0.0);
    live = tracer.advance(3.3e-5, deposits, &deposited) > 0;
    std::vector<std::uint32_t> nonzero;
    for (std::size_t i = 0; i < deposits.size(); ++i)
      if (deposits[i] != 0) nonzero.push_back(static_cast<std::uint32_t>(i));
    std::sort(deposited.begin(), deposited.end());
    ASSERT_EQ(deposited, nonzero) << "step " << steps;
    listed += deposited.size();
  }
  EXPECT_GT(steps, 3u);
  EXPECT_GT(listed, 1000u);
}

// Dropping the ended rays between budgeted steps (what the simulation does before each step)
// changes no deposit, no ledger entry and no flight length.
TEST(OpticsTracer, CompactingBetweenStepsChangesNothing) {
  Tracer kept(packing_1e4(), optics_for(20.0)), compacted(packing_1e4(), optics_for(20.0));
  const Beam beam = make_beam(BeamSpec{}, kD);
  kept.launch(beam, 1e-9), compacted.launch(beam, 1e-9);
  std::vector<double> a, b;
  int compactions = 0;
  for (int step = 0; kept.has_live_rays(); ++step) {
    const std::size_t before = compacted.save().live.size();
    compacted.compact_if_sparse();
    compactions += compacted.save().live.size() < before;
    std::fill(a.begin(), a.end(), 0.0), std::fill(b.begin(), b.end(), 0.0);
    ASSERT_EQ(kept.advance(3.3e-5, a), compacted.advance(3.3e-5, b)) << step;
    ASSERT_EQ(a, b) << step;
    ASSERT_EQ(kept.last_advance_path(), compacted.last_advance_path()) << step;
    ASSERT_EQ(kept.ledger().escaped, compacted.ledger().escaped) << step;
    ASSERT_EQ(kept.ledger().cutoff, compacted.ledger().cutoff) << step;
    ASSERT_EQ(kept.energy_in_flight(), compacted.energy_in_flight()) << step;
  }
  EXPECT_GE(compactions, 1);
}

TEST(OpticsTracer, BudgetLimitsThePathOfEveryRay) {
  Tracer tracer(packing_1e4(), optics_for(1.4));
  tracer.launch(make_beam(BeamSpec{}, kD), 1e-9);
  std::vector<double> deposits;
  // Rays start at most R_max + a hair upstream of x = 0: 1e-5 m of path meets nothing yet
  // further than that, so nothing is deposited and every ray is still live.
  tracer.advance(1e-12, deposits);
  EXPECT_EQ(tracer.hits(), 0u);
  EXPECT_TRUE(tracer.has_live_rays());
  EXPECT_LE(tracer.last_advance_path(), 1e-12);
  for (double budget : {2e-5, 7e-6}) {  // no ray travels more than the budget in one advance
    const double clock = tracer.save().clock;
    tracer.advance(budget, deposits);
    EXPECT_LE(tracer.last_advance_path(), budget * (1 + 1e-12));
    // From the rays themselves: the path clock moved by the budget, every event up to it was
    // taken (each live ray's next one lies beyond it) and no ray went past it.
    const RayState s = tracer.save();
    EXPECT_EQ(s.clock, clock + budget);
    std::size_t waiting = 0;
    for (std::size_t r = 0; r < s.live.size(); ++r) {
      if (!s.live[r]) continue;
      ASSERT_GE(s.t_next[r], 0.0) << "ray " << r << " left untraced";
      ASSERT_LE(s.start_clock[r], s.clock) << "ray " << r;
      ASSERT_GT(s.start_clock[r] + s.t_next[r], s.clock) << "ray " << r << ": an event left behind";
      ++waiting;
    }
    EXPECT_GT(waiting, 0u);  // rays are still on their way: the budget, not the flight, ended it
  }
  tracer.advance(kAll, deposits);
  EXPECT_FALSE(tracer.has_live_rays());
}

// Between budgeted advances the ledger's open part is exactly what the live rays carry: a run
// stopped mid-pulse reports it as in flight, not as an imbalance.
TEST(OpticsTracer, EnergyInFlightIsWhatTheLedgerHasNotClosed) {
  Tracer tracer(packing_1e4(), optics_for(20.0));
  tracer.launch(make_beam(BeamSpec{}, kD), 1e-9);
  std::vector<double> deposits;
  for (int step = 0; step < 6 && tracer.has_live_rays(); ++step) {
    tracer.advance(1e-4, deposits);
    const OpticsLedger& l = tracer.ledger();
    EXPECT_GT(tracer.energy_in_flight(), 0.0) << step;
    EXPECT_GT(l.absorbed, 0.0) << step;
    EXPECT_NEAR(tracer.energy_in_flight(), l.in_flight(), 1e-12 * l.injected) << step;
  }
  tracer.advance(kAll, deposits);
  EXPECT_EQ(tracer.energy_in_flight(), 0.0);
}

void expect_same_rays(const RayState& a, const RayState& b, const std::string& where);

// A step redone from a saved state gives the same deposits, and leaves every ray, the ledger,
// the clock and the counters as the first time.
TEST(OpticsTracer, SaveAndRestoreRedoAStep) {
  Tracer tracer(packing_1e4(), optics_for(1.4));
  tracer.launch(make_beam(BeamSpec{}, kD), 1e-9);
  std::vector<double> first, again;
  tracer.advance(2e-4, first);
  const RayState saved = tracer.save();
  std::vector<double> step_a, step_b;
  tracer.advance(2e-4, step_a);
  const RayState after_a = tracer.save();
  tracer.restore(saved);
  tracer.advance(2e-4, step_b);
  EXPECT_EQ(step_a, step_b);
  expect_same_rays(after_a, tracer.save(), "the redone step");
  EXPECT_GT(after_a.hits, saved.hits);  // the step did something to redo
}

std::vector<std::uint32_t> most_hit(const std::vector<double>& deposits, std::size_t count) {
  std::vector<std::uint32_t> ids(deposits.size());
  std::iota(ids.begin(), ids.end(), 0u);
  std::partial_sort(ids.begin(), ids.begin() + count, ids.end(),
                    [&](auto a, auto b) { return deposits[a] > deposits[b]; });
  ids.resize(count);
  return ids;
}

// Particles that live rays will hit after the next advance of `budget`: removing them leaves
// those rays to be traced again, in chunks that would otherwise be in free flight.
std::vector<std::uint32_t> hit_later(const RayState& s, double budget, std::size_t count) {
  std::vector<std::uint32_t> ids;
  for (std::size_t r = 0; r < s.live.size() && ids.size() < count; ++r)
    if (s.live[r] && s.t_next[r] >= 0 && s.next_particle[r] != kNoParticle &&
        s.start_clock[r] + s.t_next[r] > s.clock + budget &&
        std::find(ids.begin(), ids.end(), s.next_particle[r]) == ids.end())
      ids.push_back(s.next_particle[r]);
  return ids;
}

// Mid-pulse removal: from the moment of removal, the removed particles receive nothing.
TEST(OpticsTracer, RemovedParticleIsNeverHitAgain) {
  const Particles& p = packing_1e4();
  const Traced reference = trace(p, optics_for(20.0), BeamSpec{});
  const auto victims = most_hit(reference.deposits, 50);
  // The removal's moment on the path clock: rays are inside the packing, some heading for the
  // victims.
  const double removal = 4e-4;
  {  // Control: left in place, the victims are hit after that moment (the zeros below are the
     // removal's doing, not rays that were done with them already).
    Tracer tracer(p, optics_for(20.0));
    tracer.launch(make_beam(BeamSpec{}, kD), 1e-9);
    std::vector<double> before, after;
    tracer.advance(removal, before);
    tracer.advance(kAll, after);
    std::size_t hit_later = 0;
    for (auto v : victims) hit_later += after.size() > v && after[v] > 0.0;
    EXPECT_GE(hit_later, victims.size() / 2);  // 38 of the 50
  }
  for (SceneUpdate mode : {SceneUpdate::deferred, SceneUpdate::background, SceneUpdate::mask_only,
                           SceneUpdate::rebuild, SceneUpdate::refit, SceneUpdate::bricks}) {
    Tracer tracer(p, optics_for(20.0, true, mode));
    tracer.launch(make_beam(BeamSpec{}, kD), 1e-9);
    std::vector<double> before, after;
    tracer.advance(removal, before);
    tracer.remove_particles(victims);
    tracer.advance(kAll, after);
    for (auto v : victims) EXPECT_EQ(after.size() > v ? after[v] : 0.0, 0.0) << "particle " << v;
    const OpticsLedger& l = tracer.ledger();
    EXPECT_NEAR(l.absorbed + l.escaped + l.cutoff, l.injected, 1e-12 * l.injected);
  }
}

// After a removal in mid-flight, every segment a ray then travels ends where the brute-force
// search among the survivors says: no surviving sphere is entered before its end (the spheres
// its start lies on aside), and none ends on a removed sphere alone. Rays whose target was
// removed fly on to the next sphere behind it.
TEST(OpticsTracer, AfterARemovalInFlightEverySegmentEndsAtTheNearestSurvivor) {
  const Particles& p = packing_1e4();
  const auto victims = most_hit(trace(p, optics_for(20.0), BeamSpec{}).deposits, 50);
  std::vector<char> gone(p.size(), 0);
  for (auto v : victims) gone[v] = 1;
  Tracer tracer(p, optics_for(20.0));
  tracer.launch(make_beam(BeamSpec{}, kD), 1e-9);
  std::vector<double> deposits;
  tracer.advance(4e-4, deposits);
  tracer.remove_particles(victims);
  tracer.record_segments(true);
  while (tracer.advance(kAll, deposits) > 0) {
  }
  const std::vector<RaySegment> segments = tracer.take_segments();
  ASSERT_GT(segments.size(), 1000u);
  const double r = p.radius[0], slack = 1e-9 * r;
  auto on_sphere = [&](const Vec3& x, std::size_t i) {
    return std::abs((x - p.centre[i]).norm() - p.radius[i]) < slack;
  };
  std::size_t ends_on_survivor = 0;
  for (const RaySegment& g : segments) {
    const double length = (g.to - g.from).norm();
    const Vec3 d = (g.to - g.from) / length;
    bool on_survivor = false, on_removed = false;
    for (std::size_t i = 0; i < p.size(); ++i) {
      if (gone[i]) {
        on_removed |= on_sphere(g.to, i);
        continue;
      }
      on_survivor |= on_sphere(g.to, i);
      if (on_sphere(g.from, i)) continue;
      ASSERT_GE(ray_sphere_entry(g.from, d, p.centre[i], p.radius[i]), length - slack)
          << "segment from " << g.from.transpose() << " passes into surviving particle " << i;
    }
    EXPECT_TRUE(on_survivor || !on_removed)
        << "segment ends on a removed particle at " << g.to.transpose();
    ends_on_survivor += on_survivor;
  }
  EXPECT_GT(ends_on_survivor, segments.size() / 4);  // most end on a hit, not at the box
}

// A state saved before a removal, restored after it: its rays flying to the removed particles
// are traced again, so they still receive nothing.
TEST(OpticsTracer, ARestoredStateNeverHitsParticlesRemovedSinceItWasSaved) {
  const Particles& p = packing_1e4();
  Tracer tracer(p, optics_for(20.0));
  tracer.launch(make_beam(BeamSpec{}, kD), 1e-9);
  std::vector<double> deposits;
  tracer.advance(4e-4, deposits);
  const RayState saved = tracer.save();
  const auto victims = hit_later(saved, 0.0, 50);
  ASSERT_GE(victims.size(), 20u);
  tracer.remove_particles(victims);
  tracer.restore(saved);
  std::vector<double> after(p.size(), 0.0);
  tracer.advance(kAll, after);
  for (auto v : victims) EXPECT_EQ(after[v], 0.0) << "particle " << v;
  const OpticsLedger& l = tracer.ledger();
  EXPECT_NEAR(l.absorbed + l.escaped + l.cutoff, l.injected, 1e-12 * l.injected);
}

// Removing before tracing equals tracing a packing built without those particles (the start
// plane and the box may move by a sphere, so equality is to round-off, event for event).
TEST(OpticsTracer, RemovingThenTracingEqualsAPackingWithout) {
  const Particles& p = packing_1e4();
  const Traced reference = trace(p, optics_for(1.4), BeamSpec{});
  const auto victims = most_hit(reference.deposits, 30);
  std::vector<std::uint8_t> gone(p.size(), 0);
  for (auto v : victims) gone[v] = 1;
  Particles without;
  std::vector<std::uint32_t> new_id(p.size(), kNoParticle);
  for (std::size_t i = 0; i < p.size(); ++i)
    if (!gone[i]) new_id[i] = static_cast<std::uint32_t>(without.add(p.centre[i], p.radius[i]));
  for (SceneUpdate mode : {SceneUpdate::deferred, SceneUpdate::background, SceneUpdate::mask_only,
                           SceneUpdate::rebuild, SceneUpdate::refit, SceneUpdate::bricks})
    for (bool built : {false, true}) {  // removed before the scene's first build, or after it
      SCOPED_TRACE("scene update " + std::to_string(static_cast<int>(mode)) +
                   (built ? ", removed after the build" : ", removed before it"));
      Tracer tracer(p, optics_for(1.4, true, mode));
      if (built) tracer.build_scene();
      tracer.remove_particles(victims);
      tracer.launch(make_beam(BeamSpec{}, kD), 1e-9);
      std::vector<double> removed_run;
      tracer.advance(kAll, removed_run);
      const Traced fresh = trace(without, optics_for(1.4), BeamSpec{});
      EXPECT_EQ(tracer.hits(), fresh.hits);
      for (std::size_t i = 0; i < p.size(); ++i) {
        if (gone[i]) {
          EXPECT_EQ(removed_run[i], 0.0);
        } else {
          ASSERT_NEAR(removed_run[i], fresh.deposits[new_id[i]], 1e-12 * fresh.ledger.injected)
              << i;
        }
      }
    }
}

// Every per-ray array, the ledger and the path clock of two states.
void expect_same_rays_but_counters(const RayState& a, const RayState& b, const std::string& where) {
  ASSERT_EQ(a.polarised, b.polarised) << where;
  RayState::for_each_member(a.polarised,
                            [&](auto member) { ASSERT_TRUE(a.*member == b.*member) << where; });
  EXPECT_EQ(a.ledger.injected, b.ledger.injected) << where;
  EXPECT_EQ(a.ledger.absorbed, b.ledger.absorbed) << where;
  EXPECT_EQ(a.ledger.escaped, b.ledger.escaped) << where;
  EXPECT_EQ(a.ledger.cutoff, b.ledger.cutoff) << where;
  EXPECT_EQ(a.clock, b.clock) << where;
  EXPECT_EQ(a.live_count, b.live_count) << where;
}

// The same, and the same counters.
void expect_same_rays(const RayState& a, const RayState& b, const std::string& where) {
  expect_same_rays_but_counters(a, b, where);
  EXPECT_EQ(a.reused_primaries, b.reused_primaries) << where;
  EXPECT_EQ(a.primary_segments, b.primary_segments) << where;
  EXPECT_EQ(a.bounced_segments, b.bounced_segments) << where;
  EXPECT_EQ(a.hits, b.hits) << where;
}

// An advance runs only the chunks of rays with an event before its end. The list of next events
// it keeps from advance to advance, through removals mid-pulse, must equal one rebuilt from the
// rays (restore rebuilds it): a stale entry would leave a chunk in flight past a hit.
TEST(OpticsTracer, KeptNextEventsEqualOnesRebuiltFromTheRays) {
  const Particles& p = packing_1e4();
  const OpticsSpec spec =
      optics_for(20.0, true, OpticsSpec{}.scene_update, OpticsSpec{}.bounce_search, 64);
  Tracer kept(p, spec), rebuilt(p, spec);
  const Beam beam = make_beam(BeamSpec{}, kD);
  kept.launch(beam, 1e-9), rebuilt.launch(beam, 1e-9);
  std::vector<double> a, b;
  int step = 0;
  std::size_t run = 0, live = 0;
  bool removed = false;  // once the last advance left chunks alone: rays in flight to the victims
  bool relaunched = false;  // a second pulse while rays are live, into a part-filled chunk
  ASSERT_NE(beam.size() % 64, 0u);
  for (; kept.has_live_rays(); ++step) {
    // Relaunched when the last, part-filled chunk of 64 has live rays all in flight past the
    // next step (and no compaction comes first): only a launch that refreshes that chunk's next
    // event gets its new rays traced in time.
    const RayState now = kept.save();
    double last_chunk_event = kAll;
    for (std::size_t r = now.live.size() / 64 * 64; r < now.live.size(); ++r)
      if (now.live[r])
        last_chunk_event = std::min(last_chunk_event,
                                    now.t_next[r] < 0 ? -kAll : now.start_clock[r] + now.t_next[r]);
    if (!relaunched && now.live_count * 2 >= now.live.size() &&
        last_chunk_event > now.clock + 2e-5 && last_chunk_event < kAll) {
      kept.launch(beam, 1e-9), rebuilt.launch(beam, 1e-9);
      relaunched = true;
    }
    if (!removed && step > 0 && kept.last_chunks_run() < kept.last_chunks_live()) {
      const auto victims = hit_later(kept.save(), 2e-5, 60);
      ASSERT_GE(victims.size(), 20u);
      kept.remove_particles(victims), rebuilt.remove_particles(victims);
      removed = true;
    }
    rebuilt.restore(rebuilt.save());
    std::fill(a.begin(), a.end(), 0.0), std::fill(b.begin(), b.end(), 0.0);
    ASSERT_EQ(kept.advance(2e-5, a), rebuilt.advance(2e-5, b)) << step;
    ASSERT_EQ(a, b) << step;
    ASSERT_EQ(kept.last_advance_path(), rebuilt.last_advance_path()) << step;
    expect_same_rays(kept.save(), rebuilt.save(), "step " + std::to_string(step));
    ASSERT_EQ(kept.last_chunks_run(), rebuilt.last_chunks_run()) << step;
    run += kept.last_chunks_run(), live += kept.last_chunks_live();
  }
  EXPECT_TRUE(removed && relaunched);
  EXPECT_GT(step, 20);
  EXPECT_LT(run, live * 3 / 4);  // chunks in free flight are left alone, often
}

// The first hits of rays [first, first + count) as a launch left them: the particle each meets.
std::vector<std::uint32_t> first_hits(const RayState& s, std::size_t first, std::size_t count) {
  return {s.next_particle.begin() + static_cast<std::ptrdiff_t>(first),
          s.next_particle.begin() + static_cast<std::ptrdiff_t>(first + count)};
}

// A repeated beam's first hits are reused (OpticsSpec::reuse_primaries): pulses one after another
// and overlapping, with particles removed that the primaries hit, between pulses and during one,
// give every step the same deposits and rays as a tracer that traces each pulse's primaries. A
// launch traces again exactly the rays whose sphere is gone, and a different beam whole.
TEST(OpticsTracer, ReusedFirstHitsEqualTracedOnes) {
  const Particles& p = packing_1e4();
  OpticsSpec on = optics_for(20.0), off = on;
  off.reuse_primaries = false;
  Tracer reuse(p, on), traced(p, off);
  const Beam beam = make_beam(BeamSpec{}, kD);
  BeamSpec other_spec;
  other_spec.seed = 7;
  const Beam other = make_beam(other_spec, kD);  // as many rays, elsewhere
  ASSERT_EQ(other.size(), beam.size());
  std::vector<std::uint8_t> gone(p.size(), 0);
  std::vector<std::uint32_t> last_hits;  // beam ray k's first hit at the beam's last launch
  std::vector<double> a, b;
  for (int pulse = 0; pulse < 7; ++pulse) {
    const Beam& rays = pulse == 5 ? other : beam;
    const std::size_t reused_before = reuse.reused_primaries();
    reuse.launch(rays, 1e-9), traced.launch(rays, 1e-9);
    const std::size_t first = reuse.save().live.size() - rays.size();  // after any compaction
    // Reused: every ray of a beam launched before whose sphere is still there.
    std::size_t expected = 0;
    if (pulse > 0 && pulse != 5 && pulse != 6)
      for (std::uint32_t q : last_hits) expected += q == kNoParticle || !gone[q];
    EXPECT_EQ(reuse.reused_primaries() - reused_before, expected) << "pulse " << pulse;
    if (&rays == &beam) last_hits = first_hits(reuse.save(), first, rays.size());
    // Pulses 1 and 3 overlap the next one: it is launched after a few steps.
    const int steps = pulse == 1 || pulse == 3 ? 3 : 1000000;
    for (int step = 0; step < steps && reuse.has_live_rays(); ++step) {
      std::fill(a.begin(), a.end(), 0.0), std::fill(b.begin(), b.end(), 0.0);
      ASSERT_EQ(reuse.advance(1e-4, a), traced.advance(1e-4, b));
      ASSERT_EQ(a, b) << "pulse " << pulse << ", step " << step;
      expect_same_rays_but_counters(reuse.save(), traced.save(), "pulse " + std::to_string(pulse));
      // Removed while the pulse is in flight (pulse 2) and after it (pulses 0 and 4): every
      // tenth particle the beam's primaries hit.
      if ((pulse == 2 && step == 1) || (pulse % 4 == 0 && !reuse.has_live_rays())) {
        std::vector<std::uint32_t> victims;
        for (std::size_t k = pulse; k < last_hits.size(); k += 10)
          if (last_hits[k] != kNoParticle && !gone[last_hits[k]])
            victims.push_back(last_hits[k]), gone[last_hits[k]] = 1;
        std::sort(victims.begin(), victims.end());
        victims.erase(std::unique(victims.begin(), victims.end()), victims.end());
        ASSERT_GE(victims.size(), 10u);
        reuse.remove_particles(victims), traced.remove_particles(victims);
      }
    }
  }
  EXPECT_EQ(reuse.ledger().absorbed, traced.ledger().absorbed);
  EXPECT_EQ(reuse.hits(), traced.hits());
  EXPECT_EQ(traced.reused_primaries(), 0u);
}

// A reused first hit needs the same ray: the same point on the beam's disk, start plane and
// direction. Beams with the same disk points and direction but another start plane (the beam's
// centre moved: the rays' first hits lie at other distances), or the same start plane (the centre
// far upstream puts it at the packing's own face) but directions 1 mrad apart, share no hit; a
// beam launched again reuses its own.
TEST(OpticsTracer, AFirstHitIsReusedOnlyForTheSameRay) {
  const Particles& p = packing_1e4();
  OpticsSpec on = optics_for(1.4), off = on;
  off.reuse_primaries = false;
  const Beam near = make_beam(BeamSpec{}, kD);
  Beam along = near;
  along.centre -= 10.0 * along.direction;
  Beam tilted = along;
  tilted.direction = Vec3(1.0, 1e-3, 0.0).normalized();
  Tracer reuse(p, on), traced(p, off);
  std::vector<double> a, b;
  const Beam* beams[] = {&near, &along, &tilted, &tilted};
  const std::size_t expected[] = {0, 0, 0, tilted.size()};  // the second tilted launch reuses all
  for (int launch = 0; launch < 4; ++launch) {
    std::fill(a.begin(), a.end(), 0.0), std::fill(b.begin(), b.end(), 0.0);
    const std::uint64_t before = reuse.reused_primaries();
    reuse.launch(*beams[launch], 1e-9), traced.launch(*beams[launch], 1e-9);
    EXPECT_EQ(reuse.reused_primaries() - before, expected[launch]) << "launch " << launch;
    expect_same_rays_but_counters(reuse.save(), traced.save(), "launch " + std::to_string(launch));
    reuse.advance(kAll, a), traced.advance(kAll, b);
    ASSERT_EQ(a, b) << "launch " << launch;
  }
}

// Chunk size is a matter of speed only: in budgeted steps (chunks left alone) and whole, with
// grid or Embree bounces, every step's deposits, every ray, the ledger and the counters are the
// same for chunks of 7, 64 and 256 rays.
TEST(OpticsTracer, ChunkSizeChangesNoResult) {
  const Beam beam = make_beam(BeamSpec{}, kD);
  for (BounceSearch bounce : {BounceSearch::grid, BounceSearch::embree})
    for (double budget : {2e-5, kAll}) {
      std::vector<std::unique_ptr<Tracer>> tracers;
      for (std::size_t rays : {256u, 64u, 7u}) {
        tracers.push_back(std::make_unique<Tracer>(
            packing_1e4(), optics_for(20.0, true, OpticsSpec{}.scene_update, bounce, rays)));
        tracers.back()->launch(beam, 1e-9);
      }
      for (int step = 0; tracers[0]->has_live_rays(); ++step) {
        std::vector<std::vector<double>> deposits(tracers.size());
        for (std::size_t t = 0; t < tracers.size(); ++t) tracers[t]->advance(budget, deposits[t]);
        for (std::size_t t = 1; t < tracers.size(); ++t) {
          ASSERT_EQ(deposits[t], deposits[0]) << "step " << step << ", tracer " << t;
          expect_same_rays(tracers[t]->save(), tracers[0]->save(), "step " + std::to_string(step));
          ASSERT_EQ(tracers[t]->last_advance_path(), tracers[0]->last_advance_path()) << step;
        }
      }
    }
}

// A launch computes its own chunks' next events block by block when no chunk straddles a block
// (chunks of one ray: always; of 16: with 1024 rays, unless a compaction leaves a part chunk);
// the live rays it moves back on the clock keep theirs right too. Against a tracer that rebuilds
// every next event from the rays before each step.
TEST(OpticsTracer, ALaunchIntoWholeChunksKeepsEveryChunksNextEvent) {
  BeamSpec beam_spec;
  beam_spec.rays = 1024;
  const Beam beam = make_beam(beam_spec, kD);
  for (std::size_t chunk : {std::size_t{16}, std::size_t{1}}) {
    const OpticsSpec spec =
        optics_for(20.0, true, OpticsSpec{}.scene_update, OpticsSpec{}.bounce_search, chunk);
    Tracer kept(packing_1e4(), spec), rebuilt(packing_1e4(), spec);
    std::vector<double> a, b;
    int launches = 0;
    for (int step = 0; kept.has_live_rays() || launches == 0; ++step) {
      if (step % 3 == 0 && launches < 3) {  // every third step: a pulse into the live ones
        const bool live = kept.has_live_rays();
        ASSERT_TRUE(live || launches == 0) << "the pulses must overlap";
        kept.launch(beam, 1e-9), rebuilt.launch(beam, 1e-9);
        ++launches;
      }
      rebuilt.restore(rebuilt.save());
      std::fill(a.begin(), a.end(), 0.0), std::fill(b.begin(), b.end(), 0.0);
      ASSERT_EQ(kept.advance(2e-5, a), rebuilt.advance(2e-5, b)) << chunk << " " << step;
      ASSERT_EQ(a, b) << chunk << " " << step;
      ASSERT_EQ(kept.last_chunks_run(), rebuilt.last_chunks_run()) << chunk << " " << step;
      expect_same_rays(kept.save(), rebuilt.save(), "step " + std::to_string(step));
    }
    EXPECT_EQ(launches, 3);
  }
}

// Pulses that overlap without end (each launched while the one before is in flight): every
// launch sets the clock back to 0 and moves the live rays' segment clocks with it, so the clock
// never exceeds what the rays flew since the last launch (without it, it grows with every pulse
// and event comparisons lose eps x clock). Each live ray keeps its path to its next event.
TEST(OpticsTracer, OverlappingPulsesKeepTheClockToOnePulse) {
  Tracer tracer(packing_1e4(), optics_for(20.0));
  const Beam beam = make_beam(BeamSpec{}, kD);
  std::vector<double> deposits;
  constexpr double kStep = 2e-5;
  for (int pulse = 0; pulse < 30; ++pulse) {
    const RayState before = tracer.save();
    tracer.launch(beam, 1e-9);
    const RayState after = tracer.save();
    ASSERT_EQ(after.clock, 0.0) << pulse;
    // The rays live before the launch (compaction may have dropped ended ones: match by order).
    std::size_t w = 0;
    for (std::size_t r = 0; r < before.live.size(); ++r) {
      if (!before.live[r]) continue;
      while (!after.live[w]) ++w;
      const double path_before = before.start_clock[r] + before.t_next[r] - before.clock;
      const double path_after = after.start_clock[w] + after.t_next[w] - after.clock;
      ASSERT_NEAR(path_after, path_before, 1e-14 * (before.clock + before.t_next[r])) << pulse;
      ++w;
    }
    if (pulse > 0) {
      ASSERT_GT(before.live_count, 0u) << "the pulses must overlap";
    }
    for (int step = 0; step < 2; ++step) tracer.advance(kStep, deposits);
    ASSERT_EQ(tracer.save().clock, 2 * kStep) << pulse;
  }
  while (tracer.advance(kAll, deposits) > 0) {
  }
  const OpticsLedger& l = tracer.ledger();
  EXPECT_NEAR(l.absorbed + l.escaped + l.cutoff, l.injected, 1e-12 * l.injected);
  EXPECT_NEAR(l.injected, 30 * make_beam(BeamSpec{}, kD).power * 1e-9, 1e-12 * l.injected);
}

// The path clock: a budgeted advance moves it by the budget while rays are live, a whole one by
// the flight of the pulse; a launch with no ray live sets it back to 0, so every pulse's flight is
// measured from 0 (the step length of thermal.dt = "pulse").
TEST(OpticsTracer, ThePathClockMovesByTheBudgetAndEachPulseStartsAtZero) {
  Tracer tracer(packing_1e4(), optics_for(1.4));
  const Beam beam = make_beam(BeamSpec{}, kD);
  std::vector<double> deposits;
  tracer.launch(beam, 1e-9);
  EXPECT_EQ(tracer.save().clock, 0.0);
  tracer.advance(3e-5, deposits);
  EXPECT_EQ(tracer.save().clock, 3e-5);
  EXPECT_EQ(tracer.last_advance_path(), 3e-5);  // live rays flew the whole budget
  tracer.advance(kAll, deposits);
  EXPECT_FALSE(tracer.has_live_rays());
  const double first_flight = 3e-5 + tracer.last_advance_path();
  EXPECT_DOUBLE_EQ(tracer.save().clock, first_flight);
  tracer.launch(beam, 1e-9);
  EXPECT_EQ(tracer.save().clock, 0.0);
  tracer.advance(kAll, deposits);
  EXPECT_DOUBLE_EQ(tracer.last_advance_path(), first_flight);  // the same pulse, whole
}

// The stagger's undo: an advance taken back leaves every ray, the ledger, the counters and the
// clock as they were, through hits, ends, retraces after a removal and polarised fields; the
// advance redone equals the first. Anything else that changes the rays drops the record.
TEST(OpticsTracer, UndoAdvanceTakesBackExactlyTheLastAdvance) {
  const Particles& p = packing_1e4();
  const auto victims = most_hit(trace(p, optics_for(20.0), BeamSpec{}).deposits, 40);
  for (bool polarised : {false, true}) {
    OpticsSpec spec =
        optics_for(20.0, true, OpticsSpec{}.scene_update, OpticsSpec{}.bounce_search, 64);
    spec.polarisation.linear = polarised;
    Tracer tracer(p, spec), plain(p, spec);  // plain: each step once, no undo
    tracer.keep_undo(true);
    tracer.record_segments(true), plain.record_segments(true);
    tracer.launch(make_beam(BeamSpec{}, kD), 1e-9), plain.launch(make_beam(BeamSpec{}, kD), 1e-9);
    int step = 0, undone_with_changes = 0;
    std::vector<double> plain_deposits;
    for (; tracer.has_live_rays(); ++step) {
      const std::string where = (polarised ? "polarised, step " : "step ") + std::to_string(step);
      if (step == 12) tracer.remove_particles(victims), plain.remove_particles(victims);
      plain.advance(2e-5, plain_deposits);
      const RayState before = tracer.save();
      const double path_before = tracer.last_advance_path();
      const std::size_t run_before = tracer.last_chunks_run(),
                        live_before = tracer.last_chunks_live();
      std::vector<double> first, again;
      tracer.advance(2e-5, first);
      const RayState after = tracer.save();
      const double path_after = tracer.last_advance_path();
      tracer.undo_advance();
      expect_same_rays(tracer.save(), before, where);
      EXPECT_EQ(tracer.last_advance_path(), path_before) << where;
      EXPECT_EQ(tracer.last_chunks_run(), run_before) << where;
      EXPECT_EQ(tracer.last_chunks_live(), live_before) << where;
      undone_with_changes += !(after.t_next == before.t_next);
      tracer.advance(2e-5, again);
      ASSERT_EQ(first, again) << where;
      expect_same_rays(tracer.save(), after, where);
      EXPECT_EQ(tracer.last_advance_path(), path_after) << where;
    }
    EXPECT_GT(step, 20);
    EXPECT_GT(undone_with_changes, 10);
    // The undone advances' recorded segments went with them.
    const std::vector<RaySegment> redone = tracer.take_segments(), once = plain.take_segments();
    ASSERT_EQ(redone.size(), once.size());
    ASSERT_GT(once.size(), 1000u);
    for (std::size_t k = 0; k < once.size(); ++k)
      ASSERT_TRUE(redone[k].from == once[k].from && redone[k].to == once[k].to &&
                  redone[k].energy == once[k].energy)
          << k;
    // Launching drops the record: an undo then is refused and changes nothing; so is a second
    // undo of one advance, and an undo without keep_undo (it was a silent no-op).
    tracer.launch(make_beam(BeamSpec{}, kD), 1e-9);
    const RayState launched = tracer.save();
    EXPECT_THROW(tracer.undo_advance(), RunError);
    expect_same_rays(tracer.save(), launched, "after a launch");
    std::vector<double> deposits;
    tracer.advance(2e-5, deposits);
    tracer.undo_advance();
    EXPECT_THROW(tracer.undo_advance(), RunError);
    expect_same_rays(tracer.save(), launched, "after a second undo");
    plain.launch(make_beam(BeamSpec{}, kD), 1e-9);
    plain.advance(2e-5, deposits);
    testing::expect_error<RunError>([&] { plain.undo_advance(); },
                                    "undo_advance: no advance to undo (keep_undo(true) before it");
  }
}

// Beams along other directions than +x, wider than the sample, on a packing: every ray alone and
// the whole beam in packets against the brute-force reference (the start plane, the packets'
// tiles and the box exit all depend on the direction).
TEST(OpticsTracer, ObliqueAndReversedBeamsMatchTheReference) {
  const Vec3 directions[] = {Vec3(1, 1, 1).normalized(), -Vec3::UnitZ(),
                             Vec3(1, 0.3, -0.2).normalized()};
  for (const Vec3& d : directions) {
    BeamSpec b;
    b.direction = d;
    b.diameter_fraction = 2.0;  // wider than the sample: rays beside it escape at once
    b.rays = 400;
    const Beam beam = make_beam(b, kD);
    std::uint64_t hits = 0;
    test::expect_rays_match_reference(packing_1e4(), optics_for(1.4), beam.origin, d, hits, nullptr,
                                      1.0, 1e-9);
    EXPECT_GT(hits, beam.size() / 4) << d.transpose();  // the beam meets the packing
    test::expect_beam_matches_reference(packing_1e4(), optics_for(1.4), beam.origin, d);
  }
}

TEST(OpticsTracer, LiquidParticlesUseTheLiquidIndex) {
  // n_liquid = 1, mu = 1: R_F = 0, a liquid particle absorbs all that reaches it.
  Particles p = packing_1e4();
  for (std::size_t i = 0; i < p.size(); ++i) p.phase[i] = Phase::liquid;
  const Traced run = trace(p, optics_for(20.0), BeamSpec{});
  EXPECT_EQ(run.bounced, 0u);  // every hit absorbs everything: no reflected ray is traced
  EXPECT_LE(run.hits, 1000u);
  EXPECT_GT(run.hits, 900u);
  // reflectance(cos, 1.0) is zero to round-off (~1e-32), so rays end below the cutoff at once.
  EXPECT_LT(run.ledger.cutoff, 1e-20 * run.ledger.injected);
  EXPECT_NEAR(run.ledger.absorbed + run.ledger.escaped, run.ledger.injected,
              1e-12 * run.ledger.injected);
  // Without a cutoff too: a ray that keeps nothing of its energy ends at that hit (it flew on
  // with 0 J, bounce after bounce, and set the length of a "pulse" step).
  OpticsSpec no_cutoff = optics_for(20.0);
  no_cutoff.cutoff = 0.0;
  const Traced uncut = trace(p, no_cutoff, BeamSpec{});
  EXPECT_EQ(uncut.bounced, 0u);
  EXPECT_EQ(uncut.hits, run.hits);
  EXPECT_EQ(uncut.deposits, run.deposits);
}

// Each particle's hits take its own material's index: two spheres side by side, of materials
// n = 1.4 and n = 3, each met head-on by a pencil through its centre, absorb 1 - ((n - 1) /
// (n + 1))^2 of it (normal incidence: 97.2% and 75%); the reflections go straight back out. A
// tracer that took material 0's index for both would give the second 97.2%.
TEST(OpticsTracer, EachParticleReflectsWithItsOwnMaterialsIndex) {
  Particles p;
  p.add(Vec3(5e-4, 3e-4, 5e-4), 1e-4, 0);
  p.add(Vec3(5e-4, 7e-4, 5e-4), 1e-4, 1);
  OpticsSpec spec;
  spec.materials.resize(2);
  spec.materials[0].n_solid = {1.4, 0.0};
  spec.materials[1].n_solid = {3.0, 0.0};
  Tracer tracer(p, spec);
  const std::vector<double> energies = {1.0, 1.0};
  tracer.launch(test::custom_beam({Vec3(0, 3e-4, 5e-4), Vec3(0, 7e-4, 5e-4)}, Vec3(1, 0, 0)),
                energies);
  std::vector<double> deposits;
  tracer.advance(std::numeric_limits<double>::infinity(), deposits);
  ASSERT_EQ(tracer.hits(), 2u);
  const auto absorbed = [](double n) { return 1.0 - std::pow((n - 1.0) / (n + 1.0), 2); };
  EXPECT_NEAR(deposits[0], absorbed(1.4), 1e-15);
  EXPECT_NEAR(deposits[1], absorbed(3.0), 1e-15);
  EXPECT_NEAR(tracer.ledger().escaped, 2.0 - absorbed(1.4) - absorbed(3.0), 1e-15);
}

TEST(OpticsTracerLong, LedgerClosesOn1e5PacketWithManyRays) {
  if (!beampack::test::long_tests_asked()) GTEST_SKIP() << "set BEAMPACK_LONG=1";
  const Particles p = random_overlap_packing(100000, kD, 0.325, 9);
  BeamSpec beam;
  beam.rays = 100000;
  for (double n_hat : {1.4, 20.0}) {
    const Traced run = trace(p, optics_for(n_hat), beam);
    const OpticsLedger& l = run.ledger;
    EXPECT_NEAR(l.absorbed + l.escaped + l.cutoff, l.injected, 1e-12 * l.injected);
  }
}

}  // namespace
}  // namespace beampack

namespace beampack {
namespace {

// A polarised beam's angle keeps its meaning as the beam tilts within a face: two beams 2e-4 apart
// across |d_x| = 0.9 (where the disk axes that place the rays turn by 90 degrees) absorb the same
// to 0.5% on a cluster of 12 spheres (their rays are placed differently: unpolarised light
// differs by 0.1%), while fields at 0 and 90 degrees differ there by 8%. With the disk axes'
// frame the field turned with them, and psi = 0 absorbed as psi = 90 does.
TEST(OpticsTracer, APolarisedBeamTiltedWithinAFaceKeepsItsField) {
  Particles p;
  for (const auto& [x, y, z, r] :
       std::vector<std::array<double, 4>>{{2.928e-4, 3.684e-4, 6.506e-4, 9.075e-5},
                                          {2.971e-4, 4.666e-4, 4.895e-4, 6.118e-5},
                                          {6.173e-4, 3.068e-4, 4.456e-4, 8.617e-5},
                                          {4.653e-4, 5.434e-4, 6.189e-4, 1.169e-4},
                                          {3.921e-4, 5.743e-4, 5.981e-4, 7.049e-5},
                                          {2.507e-4, 7.367e-4, 3.992e-4, 7.198e-5},
                                          {6.959e-4, 5.426e-4, 4.857e-4, 1.041e-4},
                                          {2.652e-4, 6.035e-4, 4.371e-4, 5.636e-5},
                                          {5.803e-4, 7.157e-4, 3.536e-4, 9.411e-5},
                                          {3.991e-4, 6.209e-4, 6.111e-4, 6.531e-5},
                                          {6.649e-4, 5.788e-4, 5.914e-4, 1.074e-4},
                                          {4.643e-4, 6.294e-4, 6.892e-4, 5.716e-5}})
    p.add(Vec3(x, y, z), r);
  BeamSpec beam;
  beam.sampling = "stratified";
  beam.rays = 2000;
  const auto absorbed = [&](double dx, double psi_degrees) {
    beam.direction = Vec3(dx, 0.0, std::sqrt(1.0 - dx * dx));
    OpticsSpec spec = optics_for(2.5);
    spec.polarisation = {true, psi_degrees * std::numbers::pi / 180.0};
    return trace(p, spec, beam).ledger.absorbed;
  };
  const double below = absorbed(0.8999, 0.0), above = absorbed(0.9001, 0.0);
  EXPECT_NEAR(above, below, 5e-3 * below);
  EXPECT_GT(std::abs(absorbed(0.8999, 90.0) - below), 0.05 * below);  // the field does matter
}

// A linearly polarised beam keeps every tracer property: the ledger closes, packets and single
// rays and 1 and 2 threads give bit-identical deposits; a pulse stopped half-way and written to a
// checkpoint carries its rays' fields (continuing from the read state equals continuing
// directly); and on a packing it does absorb differently from unpolarised light.
TEST(OpticsTracer, PolarisedRaysKeepTheLedgerDeterminismAndTheirFields) {
  OpticsSpec spec = optics_for(20.0);
  spec.polarisation = {true, 0.7};
  BeamSpec beam;
  beam.rays = 3000;
  const Traced whole = trace(packing_1e4(), spec, beam);
  const OpticsLedger& l = whole.ledger;
  EXPECT_NEAR(l.absorbed + l.escaped + l.cutoff, l.injected, 1e-12 * l.injected);
  OpticsSpec single = spec;
  single.packets = false;
  EXPECT_EQ(trace(packing_1e4(), single, beam).deposits, whole.deposits);
  {
    tbb::global_control limit(tbb::global_control::max_allowed_parallelism, 1);
    EXPECT_EQ(trace(packing_1e4(), spec, beam).deposits, whole.deposits);
  }
  EXPECT_NE(trace(packing_1e4(), optics_for(20.0), beam).ledger.absorbed, l.absorbed);

  Tracer direct(packing_1e4(), spec), restored(packing_1e4(), spec);
  direct.launch(make_beam(beam, kD), 1e-9);
  std::vector<double> a, b;
  direct.advance(3e-5, a);
  StateWriter out;
  direct.save().write(out);
  StateReader in(out.finish(), "test");
  RayState state;
  state.read(in);
  ASSERT_TRUE(state.polarised);
  ASSERT_EQ(state.field.size(), state.origin.size());
  restored.restore(state);
  b = a;
  direct.advance(kAll, a);
  restored.advance(kAll, b);
  EXPECT_EQ(a, b);
}

}  // namespace
}  // namespace beampack

namespace beampack {
namespace {

// With optics.max_bounces = 1 no ray is ever bounced, so the bounce grid is not built (at 1e6
// spheres it is the largest part of the tracer's set-up); the deposits equal those of the
// Embree bounce search, which needs no grid either way.
TEST(OpticsTracer, NoBounceGridWhenNoRayCanBounce) {
  OpticsSpec one = optics_for(1.4);
  one.max_bounces = 1;
  Tracer single(packing_1e4(), one), bouncing(packing_1e4(), optics_for(1.4));
  single.build_scene(), bouncing.build_scene();
  EXPECT_FALSE(single.has_grid());
  EXPECT_TRUE(bouncing.has_grid());
  OpticsSpec embree = one;
  embree.bounce_search = BounceSearch::embree;
  const Traced a = trace(packing_1e4(), one, BeamSpec{}),
               b = trace(packing_1e4(), embree, BeamSpec{});
  EXPECT_EQ(a.deposits, b.deposits);
  EXPECT_EQ(a.bounced, 0u);
  EXPECT_GT(a.ledger.cutoff, 0.0);  // what the first hits reflect ends in the cutoff bin
}

}  // namespace
}  // namespace beampack

namespace beampack {
namespace {

// A checkpoint whose live-ray count disagrees with its rays' live flags is refused by name: the
// tracer trusts the count (a compaction with none live drops every ray without looking).
TEST(OpticsTracer, CheckpointWithAWrongLiveCountIsRefused) {
  Tracer tracer(packing_1e4(), optics_for(1.4));
  tracer.launch(make_beam(BeamSpec{}, kD), 1e-9);
  std::vector<double> deposits;
  tracer.advance(3e-5, deposits);
  RayState state = tracer.save();
  ASSERT_GT(state.live_count, 0u);
  const auto round_trip = [](const RayState& s) {
    StateWriter out;
    s.write(out);
    StateReader in(out.finish(), "test");
    RayState read;
    read.read(in);
    return read;
  };
  EXPECT_EQ(round_trip(state).live_count, state.live_count);
  state.live_count -= 1;
  testing::expect_error<InputError>([&] { round_trip(state); },
                                    "live_count = " + std::to_string(state.live_count));
  EXPECT_THROW(tracer.restore(state), InputError);  // a library caller's state, the same check
}

// A checkpoint's kept first hits are used as they are read: a hit whose normal or point is not
// finite (a damaged file, its checksum recomputed) is refused, not turned into NaN deposits.
TEST(OpticsTracer, KeptFirstHitsThatAreNotFiniteAreRefused) {
  Tracer tracer(packing_1e4(), optics_for(1.4));
  tracer.launch(make_beam(BeamSpec{}, kD), 1e-9);
  std::vector<double> deposits;
  while (tracer.advance(kAll, deposits) > 0) {
  }
  const auto round_trip = [&tracer] {
    StateWriter out;
    tracer.write_first_hits(out);
    StateReader in(out.finish(), "test");
    return tracer.read_first_hits(in);
  };
  Tracer::FirstHits hits = round_trip();
  const auto hit = std::find_if(hits.particle.begin(), hits.particle.end(),
                                [](std::uint32_t p) { return p != kNoParticle; });
  ASSERT_NE(hit, hits.particle.end());
  const auto k = static_cast<std::size_t>(hit - hits.particle.begin());
  for (const bool normal : {true, false}) {
    Tracer::FirstHits damaged = hits;
    (normal ? damaged.normal[k] : damaged.origin[k]).x() = std::nan("");
    tracer.restore_first_hits(damaged);
    SCOPED_TRACE(std::string("a first hit with a NaN ") + (normal ? "normal" : "point"));
    testing::expect_error<InputError>([&] { round_trip(); }, "first hit " + std::to_string(k));
  }
}

}  // namespace
}  // namespace beampack

namespace beampack {
namespace {

// The ray scene and the bounce grid are built on first need: a tracer that never launches (a run
// without pulses) builds neither, removing particles from it builds nothing, and an out-of-range
// id is refused at once all the same.
TEST(OpticsTracer, ATracerThatNeverTracesBuildsNoScene) {
  Tracer tracer(packing_1e4(), optics_for(1.4));
  std::vector<double> deposits;
  EXPECT_EQ(tracer.advance(kAll, deposits), 0u);
  const std::uint32_t ids[] = {3, 7};
  tracer.remove_particles(ids);
  EXPECT_FALSE(tracer.has_scene());
  EXPECT_FALSE(tracer.has_grid());
  const std::uint32_t beyond[] = {static_cast<std::uint32_t>(packing_1e4().size())};
  EXPECT_THROW(tracer.remove_particles(beyond), InputError);
  tracer.launch(make_beam(BeamSpec{}, kD), 1e-9);
  EXPECT_TRUE(tracer.has_scene());
  EXPECT_TRUE(tracer.has_grid());
  // A grid setting the build would refuse is refused with the spec (it came at the first launch).
  OpticsSpec no_cells = optics_for(1.4);
  no_cells.grid_cell_factor = 0.0;
  testing::expect_error<InputError>([&] { Tracer(packing_1e4(), no_cells); },
                                    "OpticsSpec::grid_cell_factor = 0: must be > 0");
}

// Pulses with removals in mid-flight that cross the rebuild threshold (10% of N) twice: the
// deposits and the ledger are the same to the bit whether the structure is rebuilt at once
// (deferred), on another thread and taken over whenever it lands (background), or never
// (mask_only). Which structure answers a query changes no hit, so a background build's timing
// cannot show in the results. With Embree for the bounced rays too, so they also meet it.
TEST(OpticsTracer, BackgroundRebuildsChangeNoDepositWhenTheyLand) {
  const Particles& p = packing_1e4();
  const auto ranked = most_hit(trace(p, optics_for(20.0), BeamSpec{}).deposits, 2800);
  std::vector<double> deposits[3];
  double absorbed[3];
  std::size_t rebuilds[3];
  const SceneUpdate modes[] = {SceneUpdate::deferred, SceneUpdate::background,
                               SceneUpdate::mask_only};
  for (int m = 0; m < 3; ++m) {
    SCOPED_TRACE(static_cast<int>(modes[m]));
    Tracer tracer(p, optics_for(20.0, true, modes[m], BounceSearch::embree));
    for (std::size_t pulse = 0; pulse < 4; ++pulse) {
      tracer.launch(make_beam(BeamSpec{}, kD), 1e-9);
      tracer.advance(2e-4, deposits[m]);
      const std::span<const std::uint32_t> victims(ranked.data() + 700 * pulse, 700);
      tracer.remove_particles(victims);
      tracer.advance(kAll, deposits[m]);
    }
    absorbed[m] = tracer.ledger().absorbed;
    rebuilds[m] = tracer.scene_rebuilds();
  }
  EXPECT_EQ(rebuilds[0], 2u);  // 1400 and 2800 of 10^4 removed: past 10% twice
  EXPECT_GE(rebuilds[1], 1u);  // 2 unless the first build is still in flight at the last removal
  EXPECT_LE(rebuilds[1], 2u);
  EXPECT_EQ(rebuilds[2], 0u);
  for (int m : {1, 2}) {
    EXPECT_EQ(deposits[m], deposits[0]) << static_cast<int>(modes[m]);
    EXPECT_EQ(absorbed[m], absorbed[0]) << static_cast<int>(modes[m]);
  }
}

// Built on first need or at once, the scene gives the same deposits to the bit: with particles
// dead in the arrays before the tracer took them (the build leaves them out) and removed through
// it before and after the build (the queue keeps them, the dead ones filtered), in every mode.
TEST(OpticsTracer, ALazyBuildGivesTheEagerBuildsDepositsBitForBit) {
  const Traced reference = trace(packing_1e4(), optics_for(1.4), BeamSpec{});
  const auto victims = most_hit(reference.deposits, 30);
  Particles marked = packing_1e4();
  for (std::size_t k = 0; k < 10; ++k) marked.remove(victims[k]);  // dead before either tracer
  for (SceneUpdate mode : {SceneUpdate::deferred, SceneUpdate::background, SceneUpdate::mask_only,
                           SceneUpdate::rebuild, SceneUpdate::refit, SceneUpdate::bricks}) {
    SCOPED_TRACE(static_cast<int>(mode));
    Tracer eager(marked, optics_for(1.4, true, mode)), lazy(marked, optics_for(1.4, true, mode));
    eager.build_scene();
    for (Tracer* t : {&eager, &lazy}) t->remove_particles(victims);  // 10 of them already dead
    std::vector<double> a, b;
    for (Tracer* t : {&eager, &lazy}) t->launch(make_beam(BeamSpec{}, kD), 1e-9);
    eager.advance(kAll, a);
    lazy.advance(kAll, b);
    EXPECT_EQ(a, b);
    EXPECT_EQ(eager.ledger().absorbed, lazy.ledger().absorbed);
    for (auto v : victims) EXPECT_EQ(b[v], 0.0) << v;
  }
}

// The physics runs in IEEE mode whatever mode its thread was left in (Embree's build leaves
// flush-to-zero on TBB threads): inside IeeeFloatMode a denormal survives arithmetic, and after
// it, as after KeepFloatMode, the thread has its own mode back. Without the guard results would
// depend on which thread took a chunk.
TEST(FloatMode, TheGuardsKeepDenormalsAndRestoreTheThreadsMode) {
  const float_mode::Word ieee = float_mode::read() & ~float_mode::kFlushBits;
  const float_mode::Word flushing = ieee | float_mode::kFlushBits;
  volatile double tiny = 1e-310;  // a denormal
  float_mode::write(flushing);    // as Embree leaves a TBB thread
  {
    const volatile double flushed = tiny * 0.5;
    EXPECT_EQ(flushed, 0.0);  // the mode this test set is in force
  }
  {
    const IeeeFloatMode guard;
    EXPECT_EQ(float_mode::read() & float_mode::kFlushBits, 0u);
    const volatile double half = tiny * 0.5;
    EXPECT_EQ(half, 5e-311);
  }
  EXPECT_EQ(float_mode::read(), flushing);
  {
    const KeepFloatMode keep;
    float_mode::write(ieee);  // as rtcCommitScene may
  }
  EXPECT_EQ(float_mode::read(), flushing);
  float_mode::write(ieee);
}

}  // namespace
}  // namespace beampack
