// The run says what it skipped: a stage that never ran carries the reason the loop left it out,
// and a stage that ran carries none (brief: "no stage runs unless the scene needs it").
#include <gtest/gtest.h>

#include <algorithm>
#include <array>
#include <cmath>
#include <functional>
#include <limits>
#include <string>
#include <utility>
#include <vector>

#include "engine/beam.h"
#include "engine/simulation.h"
#include "engine/state_io.h"
#include "geometry/error.h"
#include "tests/expect_error.h"
#include "tests/quick_scene.h"

namespace beampack {
namespace {

using testing::quick_scene;

// One step of each simulation, both taken whatever the first returns: true while either goes on.
bool step_both(Simulation& a, Simulation& b) {
  const bool a_goes_on = a.step();
  const bool b_goes_on = b.step();
  return a_goes_on || b_goes_on;
}

constexpr double kD = 1e-3;

// Both ledgers of a run close as the code promises (EnergyLedger): the optics one to round-off of
// the injected energy, the heat one to heat_tolerance(thermal.tolerance) of the heat moved.
void expect_ledgers_close(const Simulation& sim) {
  const EnergyLedger e = sim.figures().energy;
  ASSERT_GT(e.injected, 0.0);
  ASSERT_GT(e.absorbed, 0.0);  // the heat ledger has something to close
  EXPECT_LE(std::abs(e.optics_imbalance()), EnergyLedger::kOpticsTolerance * e.injected);
  EXPECT_LE(std::abs(e.heat_imbalance()),
            EnergyLedger::heat_tolerance(sim.spec().thermal.tolerance) * e.heat_scale())
      << "absorbed " << e.absorbed << ", stored " << e.stored << ", vaporised " << e.vaporized
      << ", walls " << e.walls << " J";
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
  EXPECT_CONTAINS(s.skipped_because, reason)
      << name << " skipped because \"" << s.skipped_because << "\", expected \"" << reason << "\"";
}

TEST(SimulationStages, AMeltingRunRunsEveryStageAndGivesNoReason) {
  Simulation sim(quick_scene());
  sim.run();
  ASSERT_GT(sim.figures().vaporized_fraction, 0.0);  // the scene needs every stage
  for (const char* name : Simulation::kStageNames) expect_ran(sim, name);
}

TEST(SimulationStages, AColdRunWithoutConductionSaysWhyItSkipsPhasesStaggerAndGraph) {
  SimulationSpec spec = quick_scene();
  spec.pulses.duration = 1e-16;  // a few kelvin: nobody melts
  spec.materials[0].conductivity = 0;
  Simulation sim(spec);
  sim.run();
  ASSERT_LT(sim.figures().max_temperature.value(), spec.materials[0].melt_temperature);
  expect_ran(sim, "trace");
  expect_ran(sim, "heat");
  expect_skipped(sim, "phases", "melting temperature");
  expect_skipped(sim, "stagger", "no phase change");
  EXPECT_EQ(sim.counts().rebuilds, 0u);
  expect_skipped(sim, "rebuild", "no conductivity, no walls");
}

// counts.heat_rows_solved is the heat stage's work done, beside heat_rows_live, the live rows a
// step could have solved (each step adds the particles live when it began). With
// thermal.skip_resting only the components with something to do are solved: in the quick scene the
// beam heats a few of 200 particles, so fewer rows than live, in a bed that conducts between its
// particles and in one that conducts only to a wall at its own temperature; without it every live
// row is. A mutation campaign dropped the sum (solved stayed 0) and no test noticed.
TEST(SimulationStages, SkippingRestingParticlesSolvesFewerThanTheLiveHeatRows) {
  Wall wall;  // at the bed's 300 K: the particles it touches rest until the beam heats them
  wall.axis = 2;
  wall.position = 0;
  wall.reach = 1e-4;
  for (const bool walls_only : {false, true}) {
    for (const bool skip : {true, false}) {
      SCOPED_TRACE(std::string(walls_only ? "a wall, no conductivity" : "conductivity") +
                   (skip ? ", skip_resting" : ", every row solved"));
      SimulationSpec spec = quick_scene();
      if (walls_only) {
        spec.materials[0].conductivity = 0;
        spec.thermal.walls = {wall};
      }
      spec.thermal.skip_resting = skip;
      Simulation sim(spec);
      std::vector<std::uint64_t> live, live_added, solved_added;  // step by step
      for (bool more = true; more;) {
        const Counts before = sim.counts();
        live.push_back(sim.particles().alive_count());
        more = sim.step();
        live_added.push_back(sim.counts().heat_rows_live - before.heat_rows_live);
        solved_added.push_back(sim.counts().heat_rows_solved - before.heat_rows_solved);
      }
      EXPECT_EQ(live_added, live);
      EXPECT_GT(*std::min_element(solved_added.begin(), solved_added.end()), 0u);  // every step's
      const Counts c = sim.counts();
      ASSERT_EQ(c.steps, 5u);
      ASSERT_GT(sim.figures().vaporized_fraction, 0.0);  // removed particles leave the live rows
      if (skip) {
        EXPECT_LT(c.heat_rows_solved, c.heat_rows_live);
      } else {
        EXPECT_EQ(c.heat_rows_solved, c.heat_rows_live);
      }
    }
  }
}

TEST(SimulationStages, NoStaggerWhenTheUserAllowsNone) {
  SimulationSpec spec = quick_scene();
  spec.max_staggers = 0;
  Simulation sim(spec);
  sim.run();
  ASSERT_GT(sim.figures().melted_fraction + sim.figures().vaporized_fraction, 0.0);
  expect_skipped(sim, "stagger", "`thermal.max_staggers` = 0");
}

TEST(SimulationStages, NoPulseSkipsTracingAndHeat) {
  SimulationSpec spec = quick_scene();
  spec.pulses.count = 0;
  Simulation sim(spec);
  sim.run();
  expect_skipped(sim, "trace", "`pulses.count` = 0: no pulse, no ray scene or bounce grid built");
  expect_skipped(sim, "heat", "`pulses.count` = 0");
  // Nor does it build what only pulses and steps use: the rays, the ray scene, the grid, the
  // contact graph.
  EXPECT_EQ(sim.beam().size(), 0u);
  EXPECT_FALSE(sim.tracer().has_scene());
  EXPECT_FALSE(sim.tracer().has_grid());
  expect_skipped(sim, "rebuild", "`pulses.count` = 0: no pulse, no contact graph built");
}

// Drawing no rays is not checking no keys: a beam key out of its range is refused all the same.
TEST(SimulationStages, NoPulseStillRefusesABadBeam) {
  SimulationSpec spec = quick_scene();
  spec.pulses.count = 0;
  spec.beam.direction = Vec3(1, 1, 0);
  testing::expect_error<InputError>([&] { Simulation sim(spec); }, "`beam.direction`");
}

// With one step per pulse flight or fixed steps alike (fixed ones ran the heat stage over no
// particle, and the phases named the melting temperature as their reason).
TEST(SimulationStages, AnEmptyPackingTracesButHasNoHeatToConduct) {
  for (double dt : {0.0, 1e-13}) {
    SimulationSpec spec = quick_scene();
    spec.packing.count = 0;
    spec.dt = dt;
    Simulation sim(spec);
    sim.run();
    expect_ran(sim, "trace");
    for (const char* stage : {"heat", "phases", "stagger"})
      expect_skipped(sim, stage, "no particles");
  }
}

// A fixed step shorter than a pulse's flight: chunks of rays whose rays are all in free flight
// through a step are left alone, and counted as such; one step per flight runs every chunk with
// a live ray. The stagger (which takes the trace back with Tracer::undo_advance) still redoes
// steps, and the ledgers close.
TEST(SimulationStages, ShortStepsLeaveChunksOfRaysInFreeFlightAlone) {
  for (double dt : {2e-15, 0.0}) {
    SimulationSpec spec = quick_scene();
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
    EXPECT_NEAR(e.absorbed + e.escaped + e.cutoff + e.in_flight, e.injected, 1e-12 * e.injected)
        << dt;
    SCOPED_TRACE("dt " + std::to_string(dt));
    expect_ledgers_close(sim);
    EXPECT_GT(e.vaporized, 0.0);  // the heat ledger's every column is in play
  }
}

// Pulses of the same rays reuse their first hits from earlier pulses, except where the sphere
// hit has vaporised since: the run (melting, vaporising, staggered, with fixed steps and one step
// per flight) is bit for bit the one that traces every pulse's primaries.
TEST(SimulationStages, RepeatedPulsesReuseFirstHitsAndChangeNothing) {
  for (double dt : {2e-15, 0.0}) {
    SimulationSpec spec = quick_scene();
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
    EXPECT_EQ(reuse.counts().segments + reuse.counts().primaries_reused, traced.counts().segments)
        << dt;
    // Reused hits carry the energy traced ones would: both runs' ledgers close, on the same
    // joules injected.
    SCOPED_TRACE("dt " + std::to_string(dt));
    expect_ledgers_close(reuse);
    expect_ledgers_close(traced);
    EXPECT_EQ(reuse.figures().energy.injected, traced.figures().energy.injected);
    EXPECT_EQ(reuse.figures().energy.absorbed, traced.figures().energy.absorbed);
  }
}

// With beam.resample each pulse's rays carry the energies of that pulse's own draw (the
// simulation keeps them with the beam): the rays a step launched start with exactly those.
TEST(SimulationStages, ResampledPulsesCarryTheirOwnRayEnergies) {
  SimulationSpec spec = quick_scene();
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
    const std::vector<double> started(
        s.initial_energy.end() - static_cast<std::ptrdiff_t>(expected.size()),
        s.initial_energy.end());
    EXPECT_EQ(started, expected) << "pulse " << launches - 1;
    redrawn += expected != first;
  }
  EXPECT_EQ(launches, 3);
  EXPECT_EQ(redrawn, 2);  // pulses 1 and 2 drew rays of their own
}

// A written state taken apart in write_state's order, to be edited and written again: a
// checksum guards the bytes, so a state with bad values must be rebuilt whole.
struct StateParts {
  std::uint32_t version = 0;
  Particles p;
  std::vector<double> absorbed;
  double time = 0, next_pulse_time = 0, peak = 0;
  int launched = 0;
  Counts counts;
  std::array<std::pair<double, std::uint64_t>, Simulation::kStages> stages{};
  RayState rays;
  std::array<double, 4> hit_frame{};  // the first hits' beam direction and start plane
  std::vector<Vec3> hit_origin, hit_normal;
  std::vector<double> hit_t;
  std::vector<std::uint32_t> hit_particle;
  std::vector<double> stored;
  ThermalLedger ledger;
  double reference = 0;
  std::vector<RaySegment> ray_paths;

  explicit StateParts(const Simulation& sim) {
    StateWriter written;
    sim.write_state(written);
    StateReader in(written.finish(), "state");
    version = in.value<std::uint32_t>();
    in.vector(p.centre), in.vector(p.radius), in.vector(p.material);
    in.vector(p.temperature), in.vector(p.phase), in.vector(p.alive);
    in.vector(absorbed);
    time = in.value<double>(), next_pulse_time = in.value<double>(), peak = in.value<double>();
    launched = in.value<int>(), counts = in.value<Counts>();
    for (auto& [seconds, calls] : stages)
      seconds = in.value<double>(), calls = in.value<std::uint64_t>();
    rays.read(in);
    for (double& v : hit_frame) v = in.value<double>();
    in.vector(hit_origin), in.vector(hit_normal), in.vector(hit_t), in.vector(hit_particle);
    in.vector(stored);
    ledger = in.value<ThermalLedger>();
    reference = in.value<double>();
    in.vector(ray_paths);
  }
  std::string bytes() const {
    StateWriter out;
    out.value(version);
    out.vector(p.centre), out.vector(p.radius), out.vector(p.material);
    out.vector(p.temperature), out.vector(p.phase), out.vector(p.alive);
    out.vector(absorbed);
    out.value(time), out.value(next_pulse_time), out.value(peak), out.value(launched),
        out.value(counts);
    for (const auto& [seconds, calls] : stages) out.value(seconds), out.value(calls);
    rays.write(out);
    for (double v : hit_frame) out.value(v);
    out.vector(hit_origin), out.vector(hit_normal), out.vector(hit_t), out.vector(hit_particle);
    out.vector(stored);
    out.value(ledger);
    out.value(reference);
    out.vector(ray_paths);
    return out.finish();
  }
};

// The InputError reading `parts` gives a simulation of `spec`, or testing::kAccepted when it
// reads.
std::string read_error(const SimulationSpec& spec, const StateParts& parts) {
  Simulation sim(spec);
  StateReader in(parts.bytes(), "rebuilt");
  return testing::error_message<InputError>([&] { sim.read_state(in); });
}

// A caller's particles at their own temperature (400 K, not the spec's 300 K), resumed as a
// library does it: saved_packing starts them at 300 K, the state sets them to where the run was.
// The heat solve measures from the coolest starting temperature, which the state keeps: built on
// 300 K, the resumed solve measured from there and ended up to 6.8e-13 K off (review finding).
TEST(SimulationStages, ACallersOwnStartingTemperaturesResumeBitForBit) {
  SimulationSpec spec = quick_scene();
  spec.dt = 4e-13;
  Particles own = random_overlap_packing(200, kD, 0.325, 7);
  for (double& t : own.temperature) t = 400.0;
  Simulation original(spec, own);
  for (int step = 0; step < 3; ++step) ASSERT_TRUE(original.step());
  StateWriter written;
  original.write_state(written);
  const std::string bytes = written.finish();
  Simulation resumed(spec, Simulation::saved_packing(StateReader(bytes, "state"), spec));
  StateReader in(bytes, "state");
  resumed.read_state(in);
  int steps = 0;
  while (step_both(resumed, original)) ++steps;
  EXPECT_GT(steps, 3);
  EXPECT_EQ(resumed.particles().temperature, original.particles().temperature);
  EXPECT_EQ(resumed.figures().energy.stored, original.figures().energy.stored);
}

// A state read into a spec whose theta_v lies at or below a live particle's temperature: the
// particle had vaporised under that spec, so the state is not one of its runs (a library caller
// lowered theta_v; the review saw 21 live particles at or above it until the next step).
TEST(SimulationStages, AStateWithALiveParticleAtTheSpecsVapourTemperatureIsRefused) {
  Simulation sim(quick_scene());
  for (int k = 0; k < 3; ++k) sim.step();
  const StateParts parts(sim);
  double hottest = 0;
  for (std::size_t i = 0; i < parts.p.size(); ++i)
    if (parts.p.alive[i]) hottest = std::max(hottest, parts.p.temperature[i]);
  ASSERT_GT(hottest, 300.0);
  SimulationSpec lower = quick_scene();
  lower.materials[0].melt_temperature =
      std::min(lower.materials[0].melt_temperature, 0.5 * hottest);
  lower.materials[0].vapor_temperature = hottest;
  EXPECT_CONTAINS(read_error(lower, parts),
                  "K and is live, at or above its material's "
                  "vapor_temperature " +
                      shown_number(hottest) + " K");
  lower.materials[0].vapor_temperature = std::nextafter(hottest, 1e300);
  EXPECT_EQ(read_error(lower, parts), testing::kAccepted);
}

// A state whose checksum holds but whose per-particle arrays do not fit the particles (a
// writer's mistake) is refused by name: a longer temperature array was copied past the
// particles'. The state is rebuilt from a real one with one temperature too many.
TEST(SimulationStages, AStateWithAnArrayOfTheWrongLengthIsRefused) {
  Simulation sim(quick_scene());
  for (int k = 0; k < 3; ++k) sim.step();
  const StateParts parts(sim);
  Simulation same(quick_scene());
  StateReader as_written(parts.bytes(), "rebuilt");
  same.read_state(as_written);  // the rebuilt state, unchanged, reads: the test rebuilds it right
  EXPECT_EQ(same.particles().temperature, sim.particles().temperature);
  StateParts longer = parts;
  longer.p.temperature.push_back(300.0);
  const std::size_t n = parts.p.size();
  EXPECT_CONTAINS(read_error(quick_scene(), longer),
                  "per-particle array holds " + std::to_string(n + 1));
}

// Nor are values a run cannot hold (a review doctored checkpoints and recomputed the checksum):
// a ray's particle index past the arrays crashed the tracer, a material id read past the
// materials, NaN reached the outputs, a pulse count beyond pulses.count ran extra rows. Each is
// refused by name, and a refused state leaves the simulation as it was.
TEST(SimulationStages, AStateWithValuesARunCannotHoldIsRefusedByName) {
  SimulationSpec spec = quick_scene();
  spec.dt = 4e-13;  // about ten steps per pulse flight: after three, rays are in flight
  Simulation sim(spec);
  for (int k = 0; k < 3; ++k) sim.step();
  const StateParts parts(sim);
  ASSERT_GT(parts.rays.live_count, 0u);
  ASSERT_EQ(read_error(spec, parts), testing::kAccepted);
  const std::size_t live = std::size_t(
      std::find(parts.rays.live.begin(), parts.rays.live.end(), 1) - parts.rays.live.begin());
  const double nan = std::numeric_limits<double>::quiet_NaN();
  const std::vector<std::pair<std::function<void(StateParts&)>, std::string>> edits =
      {
          {[](StateParts& s) { s.p.material[3] = 99; }, "particle 3 has material 99 of 1"},
          {[&](StateParts& s) { s.p.temperature[4] = nan; }, "particle 4 has temperature nan K"},
          {[](StateParts& s) { s.p.temperature[4] = -50; }, "particle 4 has temperature -50"},
          {[](StateParts& s) { s.p.phase[5] = Phase(7); },
           "particle 5 has a phase or live flag out of range"},
          {[](StateParts& s) { s.p.alive[5] = 2; },
           "particle 5 has a phase or live flag out of range"},
          {[&](StateParts& s) { s.absorbed[6] = nan; }, "particle 6 has absorbed nan J"},
          {[&](StateParts& s) { s.stored[6] = nan; }, "particle 6 has stored heat nan J"},
          {[&](StateParts& s) { s.time = nan; }, "its time, next pulse time or peak"},
          {[&](StateParts& s) { s.peak = nan; }, "its time, next pulse time or peak"},
          {[](StateParts& s) { s.launched = 99; }, "99 pulses launched, of pulses.count = 5"},
          // Waited for without end (a run of 1e-11 s took no pulse in 15 s).
          {[](StateParts& s) { s.next_pulse_time = 1e300; },
           "next pulse time 1e+300 s after 1 pulses of period 0 s"},
          {[](StateParts& s) { s.peak = -1e308; }, "K, above the run's peak"},
          {[](StateParts& s) { s.p.phase[8] = Phase::vapor; },
           "particle 8 has phase vapor and is live"},
          {[](StateParts& s) { s.p.alive[8] = 0; }, "particle 8 has been removed unvaporised"},
          {[&](StateParts& s) { s.counts.max_pulse_delay = nan; }, "longest pulse delay is nan"},
          {[](StateParts& s) { s.launched = -5; }, "-5 pulses launched"},
          // Rays before any launch: a spec without pulses would trace and heat them unconducted.
          {[](StateParts& s) { s.launched = 0; }, "live rays and no pulse launched"},
          {[](StateParts& s) { s.counts.particles = 7; }, "its counts are of 7 particles"},
          {[&](StateParts& s) { s.ledger.walls = nan; }, "a heat ledger entry is nan"},
          {[&](StateParts& s) { s.reference = nan; }, "reference temperature is nan K"},
          {[&](StateParts& s) { s.stages[1].first = nan; }, "a stage time is not finite"},
          {[&](StateParts& s) { s.rays.next_particle[live] = 5'000'000; },
           "ray " + std::to_string(live) + " has particle 5000000, beyond the 200 particles"},
          {[&](StateParts& s) { s.rays.last_particle[live] = 200; },
           "has particle 200, beyond the 200"},
          {[&](StateParts& s) { s.rays.energy[live] = nan; },
           "ray " + std::to_string(live) + " has energy nan"},
          {[&](StateParts& s) { s.rays.energy[live] = 2 * s.rays.initial_energy[live]; },
           " has energy "},
          {[&](StateParts& s) { s.rays.start_clock[live] = nan; },
           "clock that is not a finite number"},
          {[&](StateParts& s) { s.rays.ledger.escaped = -1; }, "a ledger entry or the clock is -1"},
          {[&](StateParts& s) { s.hit_t.front() = nan; }, "a first hit at distance nan"},
          {[&](StateParts& s) {
    s.ray_paths.push_back({Vec3(nan, 0, 0), Vec3::Zero(), 1e-12});
           },
           "a recorded ray path holds a value that is not a finite number"},
  };
  ASSERT_FALSE(parts.hit_t.empty());
  for (const auto& [edit, message] : edits) {
    StateParts bad = parts;
    edit(bad);
    const std::string error = read_error(spec, bad);
    EXPECT_CONTAINS(error, "checkpoint: ") << message << ": " << error;
    EXPECT_CONTAINS(error, message) << message << ": " << error;
  }
  // A resumed run builds its scene from the state's particles (no packing file): they pass the
  // checks a packing file's rows do.
  // As a library does it: a simulation built from the state's own particles continues as the one
  // that wrote it.
  SimulationSpec warm = spec;
  warm.packing.initial_temperature = 450.0;
  EXPECT_EQ(Simulation::saved_packing(StateReader(parts.bytes(), "rebuilt"), warm).temperature,
            std::vector<double>(parts.p.size(), 450.0));  // as a new run of the spec starts them
  const Particles saved = Simulation::saved_packing(StateReader(parts.bytes(), "rebuilt"), spec);
  EXPECT_EQ(saved.centre, parts.p.centre);
  {
    Simulation resumed(spec, saved);
    StateReader in(parts.bytes(), "rebuilt");
    resumed.read_state(in);
    Simulation original = Simulation(spec);
    StateReader again(parts.bytes(), "rebuilt");
    original.read_state(again);
    while (step_both(resumed, original)) {
    }
    EXPECT_EQ(resumed.particles().temperature, original.particles().temperature);
    EXPECT_EQ(resumed.figures().energy.absorbed, original.figures().energy.absorbed);
  }
  for (const auto& edit : std::vector<std::function<void(StateParts&)>>{
           [&](StateParts& s) { s.p.centre[8].y() = nan; },
           [](StateParts& s) { s.p.radius[8] = -1; }, [](StateParts& s) { s.p.radius[8] = 0; }}) {
    StateParts bad = parts;
    edit(bad);
    testing::expect_error<InputError>(
        [&] { Simulation::saved_packing(StateReader(bad.bytes(), "rebuilt"), spec); },
        "checkpoint: particle 8: ");
  }
  // Nor a material the spec does not define: named as the checkpoint's (the tracer would refuse
  // it as if the run file were wrong).
  {
    StateParts bad = parts;
    bad.p.material[3] = 9;
    testing::expect_error<InputError>(
        [&] { Simulation::saved_packing(StateReader(bad.bytes(), "rebuilt"), spec); },
        "checkpoint: particle 3 has material 9 of 1");
  }
  // A refused state changes nothing: the simulation goes on as if it had never read it.
  Simulation kept(spec), fresh(spec);
  StateParts bad = parts;
  bad.rays.next_particle[live] = 5'000'000;
  StateReader in(bad.bytes(), "rebuilt");
  EXPECT_THROW(kept.read_state(in), InputError);
  while (step_both(kept, fresh)) {
  }
  EXPECT_EQ(kept.particles().temperature, fresh.particles().temperature);
  EXPECT_EQ(kept.figures().time, fresh.figures().time);
  EXPECT_EQ(kept.counts().segments, fresh.counts().segments);
}

TEST(SimulationStages, BeforeTheFirstStepNothingHasRunYet) {
  Simulation sim(quick_scene());
  expect_skipped(sim, "trace", "no step taken yet");
  expect_ran(sim, "rebuild");  // the contact graph is built with the scene
}

}  // namespace
}  // namespace beampack

namespace beampack {
namespace {

// One pulse of `duration` seconds from a wide flat beam on the 1 mm cube.
SimulationSpec flat_beam_pulse(double duration) {
  SimulationSpec spec;
  spec.packing.sample_size = kD;
  spec.beam.profile = "flat";
  spec.beam.sampling = "stratified";
  spec.beam.rays = 4000;
  spec.pulses.count = 1;
  spec.pulses.duration = duration;
  return spec;
}

// One sphere of radius 0.1 mm in the middle of the cube, at `temperature` K.
Particles one_sphere_at(double temperature) {
  Particles one;
  one.add(Vec3::Constant(0.5 * kD), 0.1e-3);
  one.temperature[0] = temperature;
  return one;
}

// One sphere under a wide flat beam, heated from 300 K past theta_v in one step: it melted on the
// way, so the rays must meet it as liquid (n_l = 1, R_F = 0: it absorbs every ray that meets it),
// which takes one redo of the step. Before, only solid <-> liquid changes asked for the redo.
TEST(SimulationStages, ASphereVaporisedFromSolidInOneStepIsRetracedAsLiquid) {
  SimulationSpec spec = flat_beam_pulse(1e-10);  // ~6e4 K for the sphere's share of the beam
  const Particles one = one_sphere_at(300.0);
  const double R = one.radius[0];
  const Vec3 centre = one.centre[0];
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

// A liquid sphere (690 K, theta_v = 700 K) vaporised in one step was traced as liquid, and a
// vaporised particle is still met as liquid until it leaves the scene (Remark 10): the optics the
// rays met did not change, so the step is not redone. Seen as a change of index (vapour against
// liquid), it was redone once for nothing, and the stagger stage ran on every such step.
TEST(SimulationStages, ALiquidSphereThatVaporisesIsNotRetraced) {
  SimulationSpec spec = flat_beam_pulse(1e-12);  // ~200 K for the sphere's share of the beam
  const Particles one = one_sphere_at(690.0);
  Simulation sim(spec, one);
  ASSERT_EQ(sim.figures().melted_fraction, 1.0);
  sim.run();
  ASSERT_EQ(sim.figures().vaporized_fraction, 1.0);
  EXPECT_EQ(sim.counts().staggers, 0u);
  EXPECT_EQ(sim.counts().stagger_cycles + sim.counts().capped_stagger_steps, 0u);
  expect_skipped(sim, "stagger", "no phase change altered the optics");
  // As liquid (n_l = 1, R_F = 0) it took every ray that met it, as the same sphere does without
  // the stagger.
  spec.max_staggers = 0;
  Simulation unstaggered(spec, one);
  unstaggered.run();
  EXPECT_EQ(sim.absorbed(), unstaggered.absorbed());
  EXPECT_EQ(sim.figures().energy.escaped, unstaggered.figures().energy.escaped);
}

// A sphere 2.6 K below theta_m, liquid index 3 (it lets in a fifth less than the solid's 1.4):
// traced solid it melts, traced liquid it stays solid. The redo alternates, and the cycle is
// found at its second pass, the first redo: one redo, one cycle of one particle, and the step keeps
// that redo's result (traced liquid: solid, with what the liquid index lets in). Found one pass
// later, the step was redone twice and kept the first pass's result again (melted).
TEST(SimulationStages, AStaggerCycleStopsAfterItsFirstRedo) {
  SimulationSpec spec = flat_beam_pulse(1e-14);
  spec.optics.materials[0].n_liquid = 3;
  const Particles one = one_sphere_at(597.4);
  // The two passes of the cycle, each run alone: traced solid it melts, traced liquid it does not.
  SimulationSpec as_solid = spec;
  as_solid.max_staggers = 0;
  Simulation solid(as_solid, one);
  solid.run();
  ASSERT_EQ(solid.particles().phase[0], Phase::liquid);
  SimulationSpec as_liquid = as_solid;
  as_liquid.optics.materials[0].n_solid = as_liquid.optics.materials[0].n_liquid;
  Simulation liquid(as_liquid, one);
  liquid.run();
  ASSERT_EQ(liquid.particles().phase[0], Phase::solid);
  ASSERT_LT(liquid.absorbed()[0], 0.9 * solid.absorbed()[0]);

  for (const int cap : {2, 4, 9}) {
    spec.max_staggers = cap;
    Simulation sim(spec, one);
    sim.run();
    const Counts c = sim.counts();
    EXPECT_EQ(c.steps, 1u) << cap;
    EXPECT_EQ(c.staggers, 1u) << cap;
    EXPECT_EQ(c.stagger_cycles, 1u) << cap;
    EXPECT_EQ(c.stagger_cycle_particles, 1u) << cap;
    EXPECT_EQ(c.capped_stagger_steps, 0u) << cap;
    EXPECT_EQ(sim.particles().phase[0], Phase::solid) << cap;
    EXPECT_EQ(sim.absorbed()[0], liquid.absorbed()[0]) << cap;
    EXPECT_EQ(sim.particles().temperature[0], liquid.particles().temperature[0]) << cap;
  }
}

// A run of fixed steps and a period in seconds (no conduction), with the step count at which each
// pulse after the first started (pulse k - 1 ends as pulse k starts; the last ends with the run).
struct PulseStarts {
  Counts counts;
  double time = 0;
  std::vector<std::uint64_t> steps;
};
PulseStarts pulse_starts(double dt, double period, int pulses) {
  SimulationSpec spec = quick_scene();
  spec.materials[0].conductivity = 0.0;
  spec.dt = dt;
  spec.pulses.period = period;
  spec.pulses.count = pulses;
  Simulation sim(spec, random_overlap_packing(200, kD, 0.325, 7));
  PulseStarts out;
  sim.on_pulse_end([&](int) { out.steps.push_back(sim.counts().steps); });
  sim.run();
  out.counts = sim.counts();
  out.time = sim.figures().time;
  out.steps.pop_back();  // the last pulse's end: the run's
  return out;
}

// Pulse k is due at k T_p; with T_p exactly 30000 fixed steps every pulse starts on time. The
// clock, summed step by step, drifted by ~1e-16 a step, beyond the due test's 1e-12 slack: the
// fourth pulse started one step late (max_pulse_delay = dt).
TEST(SimulationStages, PulsesDueOnAStepBoundaryStartOnItAfterManySteps) {
  const double dt = 1e-15;
  const PulseStarts run = pulse_starts(dt, 3e-11, 4);
  EXPECT_LT(run.counts.max_pulse_delay, 1e-6 * dt);
  EXPECT_EQ(run.counts.late_pulses, 0u);
  EXPECT_EQ(run.steps, (std::vector<std::uint64_t>{30000, 60000, 90000}));
  EXPECT_EQ(run.time, double(run.counts.steps) * dt);
}

// A step twice the period: at each step boundary the two pulses due by then start (found by an
// audit: one pulse per step started pulse k at k dt, not at the first boundary after k T_p, and the
// delay grew with k: 2.5e-11 s for pulse 5 here).
TEST(SimulationStages, EveryPulseDueByAStepBoundaryStartsOnIt) {
  const double dt = 1e-11, period = 5e-12;
  const PulseStarts run = pulse_starts(dt, period, 6);
  EXPECT_EQ(run.counts.rays, 6u * quick_scene().beam.rays);
  EXPECT_EQ(run.steps, (std::vector<std::uint64_t>{1, 1, 2, 2, 3}));  // k T_p rounded up to dt
  EXPECT_LE(run.counts.max_pulse_delay, (dt - period) * (1 + 1e-9));
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
  SimulationSpec spec = quick_scene();
  spec.beam.rays = 1;
  spec.beam.decay = 1000;
  spec.beam.seed = 1;
  spec.pulses.count = 3;
  ASSERT_NO_THROW(make_beam(spec.beam, kD, 0));
  spec.beam.resample = true;
  testing::expect_error<InputError>([&] { Simulation sim(spec); },
                                    "pulse 2's rays (`beam.resample`)");
}

}  // namespace
}  // namespace beampack
