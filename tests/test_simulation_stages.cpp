// The run says what it skipped: a stage that never ran carries the reason the loop left it out,
// and a stage that ran carries none (brief: "no stage runs unless the scene needs it").
#include <gtest/gtest.h>

#include <string>

#include "engine/beam.h"
#include "engine/simulation.h"
#include "engine/state_io.h"
#include "geometry/error.h"

namespace beampack {
namespace {

constexpr double kD = 1e-3;

// The `quick` preset's scene: 200 spheres, 200 rays, pulses long enough to melt and vaporise.
SimulationSpec quick_spec() {
  SimulationSpec s;
  s.packing.sample_size = kD;
  s.packing.count = 200;
  s.packing.seed = 7;
  s.beam.rays = 200;
  s.beam.seed = 7;
  s.pulses.count = 5;
  s.pulses.duration = 3e-13;
  s.materials[0].conductivity = 20.0;
  return s;
}

StageTime stage(const Simulation& sim, const std::string& name) {
  for (int k = 0; k < Simulation::kStages; ++k)
    if (name == Simulation::kStageNames[k]) return sim.stages()[k];
  ADD_FAILURE() << "no stage " << name;
  return {};
}

void expect_ran(const Simulation& sim, const std::string& name) {
  const StageTime s = stage(sim, name);
  EXPECT_GT(s.calls, 0u) << name;
  EXPECT_EQ(s.skipped_because, "") << name;
}

void expect_skipped(const Simulation& sim, const std::string& name, const std::string& reason) {
  const StageTime s = stage(sim, name);
  EXPECT_EQ(s.calls, 0u) << name;
  EXPECT_EQ(s.seconds, 0.0) << name;
  EXPECT_NE(s.skipped_because.find(reason), std::string::npos)
      << name << " skipped because \"" << s.skipped_because << "\", expected \"" << reason << "\"";
}

TEST(SimulationStages, AMeltingRunRunsEveryStageAndGivesNoReason) {
  Simulation sim(quick_spec());
  sim.run();
  ASSERT_GT(sim.figures().vaporized_fraction, 0.0);  // the scene needs every stage
  for (const char* name : Simulation::kStageNames) expect_ran(sim, name);
}

TEST(SimulationStages, AColdRunWithoutConductionSaysWhyItSkipsPhasesStaggerAndGraph) {
  SimulationSpec spec = quick_spec();
  spec.pulses.duration = 1e-16;  // a few kelvin: nobody melts
  spec.materials[0].conductivity = 0;
  Simulation sim(spec);
  sim.run();
  ASSERT_LT(sim.figures().max_temperature, spec.materials[0].melt_temperature);
  expect_ran(sim, "trace");
  expect_ran(sim, "heat");
  expect_skipped(sim, "phases", "melting temperature");
  expect_skipped(sim, "stagger", "no phase change");
  EXPECT_EQ(sim.counts().rebuilds, 0u);
  expect_skipped(sim, "rebuild", "no conductivity, no walls");
}

TEST(SimulationStages, NoStaggerWhenTheUserAllowsNone) {
  SimulationSpec spec = quick_spec();
  spec.max_staggers = 0;
  Simulation sim(spec);
  sim.run();
  ASSERT_GT(sim.figures().melted_fraction + sim.figures().vaporized_fraction, 0.0);
  expect_skipped(sim, "stagger", "`thermal.max_staggers` = 0");
}

TEST(SimulationStages, NoPulseSkipsTracingAndHeat) {
  SimulationSpec spec = quick_spec();
  spec.pulses.count = 0;
  Simulation sim(spec);
  sim.run();
  expect_skipped(sim, "trace", "`pulses.count` = 0");
  expect_skipped(sim, "heat", "`pulses.count` = 0");
}

TEST(SimulationStages, AnEmptyPackingTracesButHasNoHeatToConduct) {
  SimulationSpec spec = quick_spec();
  spec.packing.count = 0;
  Simulation sim(spec);
  sim.run();
  expect_ran(sim, "trace");
  expect_skipped(sim, "heat", "no particles");
  expect_skipped(sim, "phases", "melting temperature");
}

// A fixed step shorter than a pulse's flight: chunks of rays whose rays are all in free flight
// through a step are left alone, and counted as such; one step per flight runs every chunk with
// a live ray. The stagger (which takes the trace back with Tracer::undo_advance) still redoes
// steps, and the ledgers close.
TEST(SimulationStages, ShortStepsLeaveChunksOfRaysInFreeFlightAlone) {
  for (double dt : {2e-15, 0.0}) {
    SimulationSpec spec = quick_spec();
    spec.beam.rays = 2000;
    spec.dt = dt;
    Simulation sim(spec);
    sim.run();
    const Counts c = sim.counts();
    ASSERT_GT(c.ray_chunks_live, 0u) << dt;
    if (dt > 0) {
      EXPECT_LT(c.ray_chunks_run, c.ray_chunks_live / 2) << dt;
      EXPECT_GT(c.staggers, 0u);
    } else {
      EXPECT_EQ(c.ray_chunks_run, c.ray_chunks_live);
    }
    const EnergyLedger& e = sim.figures().energy;
    EXPECT_NEAR(e.absorbed + e.escaped + e.cutoff + e.in_flight, e.injected, 1e-12 * e.injected) << dt;
  }
}

// Pulses of the same rays reuse their first hits from earlier pulses, except where the sphere
// hit has vaporised since: the run (melting, vaporising, staggered, with fixed steps and one step
// per flight) is bit for bit the one that traces every pulse's primaries.
TEST(SimulationStages, RepeatedPulsesReuseFirstHitsAndChangeNothing) {
  for (double dt : {2e-15, 0.0}) {
    SimulationSpec spec = quick_spec();
    spec.dt = dt;
    Simulation reuse(spec);
    spec.optics.reuse_primaries = false;
    Simulation traced(spec);
    reuse.run(), traced.run();
    ASSERT_GT(reuse.counts().rebuilds, 0u) << dt;  // spheres the rays met vaporised
    EXPECT_GT(reuse.counts().staggers, 0u) << dt;
    EXPECT_EQ(reuse.absorbed(), traced.absorbed()) << dt;
    EXPECT_EQ(reuse.particles().temperature, traced.particles().temperature) << dt;
    EXPECT_EQ(reuse.particles().phase, traced.particles().phase) << dt;
    EXPECT_EQ(reuse.figures().energy.escaped, traced.figures().energy.escaped) << dt;
    EXPECT_EQ(reuse.figures().time, traced.figures().time) << dt;
    // Pulses 1-4 reuse all but the rays whose sphere vaporised: most of 4 x 200.
    EXPECT_GT(reuse.counts().primaries_reused, 400u) << dt;
    EXPECT_LT(reuse.counts().primaries_reused, 800u) << dt;
    EXPECT_EQ(traced.counts().primaries_reused, 0u) << dt;
    EXPECT_EQ(reuse.counts().segments + reuse.counts().primaries_reused, traced.counts().segments) << dt;
  }
}

// With beam.resample each pulse's rays carry the energies of that pulse's own draw (the
// simulation keeps them with the beam): the rays a step launched start with exactly those.
TEST(SimulationStages, ResampledPulsesCarryTheirOwnRayEnergies) {
  SimulationSpec spec = quick_spec();
  spec.beam.resample = true;
  spec.pulses.count = 3;
  Simulation sim(spec);
  const std::vector<double> first = sim.beam().ray_energies(spec.pulses.duration);
  std::uint64_t rays = 0;
  int launches = 0, redrawn = 0;
  for (bool more = true; more;) {
    more = sim.step();
    if (sim.counts().rays == rays) continue;  // no launch this step
    rays = sim.counts().rays;
    ++launches;
    const std::vector<double> expected = sim.beam().ray_energies(spec.pulses.duration);
    const RayState s = sim.tracer().save();
    ASSERT_GE(s.initial_energy.size(), expected.size());
    const std::vector<double> started(s.initial_energy.end() - static_cast<std::ptrdiff_t>(expected.size()),
                                      s.initial_energy.end());
    EXPECT_EQ(started, expected) << "pulse " << launches - 1;
    redrawn += expected != first;
  }
  EXPECT_EQ(launches, 3);
  EXPECT_EQ(redrawn, 2);  // pulses 1 and 2 drew rays of their own
}

// A state whose checksum holds but whose per-particle arrays do not fit the particles (a
// writer's mistake) is refused by name: a longer temperature array was copied past the
// particles'. The state is rebuilt from a real one with one temperature too many.
TEST(SimulationStages, AStateWithAnArrayOfTheWrongLengthIsRefused) {
  Simulation sim(quick_spec());
  for (int k = 0; k < 3; ++k) sim.step();
  StateWriter written;
  sim.write_state(written);
  const std::string bytes = written.finish();
  StateReader in(bytes, "state");
  const auto version = in.value<std::uint32_t>();
  Particles p;
  in.vector(p.centre), in.vector(p.radius), in.vector(p.material);
  in.vector(p.temperature), in.vector(p.phase), in.vector(p.alive);
  // What follows the six arrays, byte for byte: after the layout tag (4 + 3 bytes), the version
  // and the arrays (each its length and values), up to the checksum (8 bytes).
  const std::size_t n = p.size(), tag = 7, checksum = 8;
  const std::size_t head = tag + sizeof version + 6 * sizeof(std::uint64_t) + n * sizeof(Vec3) +
                     n * sizeof(double) * 2 + n * sizeof(p.material[0]) + n * sizeof(p.phase[0]) +
                     n * sizeof(p.alive[0]);
  const std::string rest = bytes.substr(head, bytes.size() - head - checksum);
  auto state_with = [&](std::size_t temperatures) {
    StateWriter out;
    out.value(version);
    std::vector<double> t = p.temperature;
    t.resize(temperatures, 300.0);
    out.vector(p.centre), out.vector(p.radius), out.vector(p.material);
    out.vector(t), out.vector(p.phase), out.vector(p.alive);
    for (char c : rest) out.value(c);
    return out.finish();
  };
  Simulation same(quick_spec());
  StateReader as_written(state_with(n), "rebuilt");
  same.read_state(as_written);  // the rebuilt state, unchanged, reads: the test rebuilds it right
  EXPECT_EQ(same.particles().temperature, sim.particles().temperature);
  Simulation other(quick_spec());
  StateReader longer(state_with(n + 1), "longer");
  try {
    other.read_state(longer);
    ADD_FAILURE() << "a state with " << n + 1 << " temperatures for " << n << " particles was read";
  } catch (const InputError& e) {
    EXPECT_NE(std::string(e.what()).find("per-particle array holds " + std::to_string(n + 1)), std::string::npos)
        << e.what();
  }
}

TEST(SimulationStages, BeforeTheFirstStepNothingHasRunYet) {
  Simulation sim(quick_spec());
  expect_skipped(sim, "trace", "no step taken yet");
  expect_ran(sim, "rebuild");  // the contact graph is built with the scene
}

}  // namespace
}  // namespace beampack

namespace beampack {
namespace {

// One sphere under a wide flat beam, heated from 300 K past theta_v in one step: it melted on the
// way, so the rays must meet it as liquid (n_l = 1, R_F = 0: it absorbs every ray that meets it),
// which takes one redo of the step. Before, only solid <-> liquid changes asked for the redo.
TEST(SimulationStages, ASphereVaporisedFromSolidInOneStepIsRetracedAsLiquid) {
  SimulationSpec spec;
  spec.packing.sample_size = kD;
  spec.beam.profile = "flat";
  spec.beam.sampling = "stratified";
  spec.beam.rays = 4000;
  spec.pulses.count = 1;
  spec.pulses.duration = 1e-10;  // ~6e4 K for the sphere's share of the beam
  const double R = 0.1e-3;
  const Vec3 centre = Vec3::Constant(0.5 * kD);
  Particles one;
  one.add(centre, R);
  const Beam beam = make_beam(spec.beam, kD);
  const std::vector<double> energy = beam.ray_energies(spec.pulses.duration);
  double met = 0;  // the energy of the rays whose line passes through the sphere
  for (std::size_t k = 0; k < beam.size(); ++k) {
    const Vec3 off = beam.origin[k] - centre;
    if ((off - off.dot(beam.direction) * beam.direction).norm() < R) met += energy[k];
  }
  Simulation sim(spec, one);
  sim.run();
  ASSERT_EQ(sim.figures().vaporized_fraction, 1.0);
  EXPECT_EQ(sim.counts().staggers, 1u);
  EXPECT_NEAR(sim.absorbed()[0], met, 1e-12 * met);

  spec.max_staggers = 0;  // as solid: Fresnel reflection keeps a visible share out
  Simulation solid(spec, one);
  solid.run();
  EXPECT_LT(solid.absorbed()[0], 0.97 * met);
}

// thermal.dt = "pulse": one step is the pulse's whole flight. A flat beam on one sphere in the
// middle of the cube: the rays that miss it fly from the start plane (R upstream of the sphere)
// across its box (2R), those that hit it end there or bounce out within the box: the step lasts
// between (D/2 + R) / c and (D/2 + 3R) / c.
TEST(SimulationStages, APulseStepLastsTheRaysFlight) {
  SimulationSpec spec;
  spec.packing.sample_size = kD;
  spec.beam.rays = 2000;
  spec.beam.sampling = "stratified";
  spec.beam.profile = "flat";
  spec.pulses.count = 1;
  spec.pulses.duration = 1e-15;
  const double R = 0.12e-3;
  Particles p;
  p.add(Vec3::Constant(0.5 * kD), R);
  Simulation sim(spec, p);
  sim.run();
  EXPECT_EQ(sim.counts().steps, 1u);
  EXPECT_GE(sim.figures().time, (0.5 * kD + R) / kSpeedOfLight * (1 - 1e-12));
  EXPECT_LE(sim.figures().time, (0.5 * kD + 3 * R) / kSpeedOfLight);
}

// beam.resample with a profile too narrow for its rays: pulse 0's draw happens to sample it,
// pulse 2's does not. Refused as input when the run is set up, naming the pulse, not found
// mid-run (where it ended the run without its outputs).
TEST(SimulationStages, AResampledPulseThatCannotSampleTheProfileIsRefusedUpFront) {
  SimulationSpec spec = quick_spec();
  spec.beam.rays = 1;
  spec.beam.decay = 1000;
  spec.beam.seed = 1;
  spec.pulses.count = 3;
  ASSERT_NO_THROW(make_beam(spec.beam, kD, 0));
  spec.beam.resample = true;
  try {
    Simulation sim(spec);
    FAIL() << "accepted";
  } catch (const InputError& e) {
    EXPECT_NE(std::string(e.what()).find("pulse 2's rays (`beam.resample`)"), std::string::npos) << e.what();
  }
}

}  // namespace
}  // namespace beampack
