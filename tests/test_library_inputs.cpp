// A library caller's inputs are checked as the run file's are: particles, the simulation's own
// numbers and a hand-made launch are refused by name (InputError), never a crash, a NaN ledger
// or a silent reading (a library review found each of these running).
#include <gtest/gtest.h>

#include <cmath>
#include <functional>
#include <limits>
#include <numbers>
#include <sstream>
#include <stdexcept>
#include <string>
#include <vector>

#include "engine/beam.h"
#include "engine/memory_need.h"
#include "engine/simulation.h"
#include "engine/state_io.h"
#include "engine/tracer.h"
#include "geometry/compensated_sum.h"
#include "geometry/contact.h"
#include "geometry/error.h"
#include "geometry/packing.h"
#include "tests/expect_error.h"
#include "tests/quick_scene.h"
#include "thermal/thermal_model.h"

namespace beampack {
namespace {

constexpr double kD = 1e-3;
constexpr double kNaN = std::numeric_limits<double>::quiet_NaN();

Particles three_spheres() {
  Particles p;
  for (int k = 0; k < 3; ++k) p.add(Vec3(0.3e-3 + 0.2e-3 * k, 0.5e-3, 0.5e-3), 1e-4);
  return p;
}

SimulationSpec one_pulse() {
  SimulationSpec s;
  s.packing.sample_size = kD;
  s.beam.rays = 100;
  s.pulses.count = 1;
  s.pulses.duration = 1e-13;
  return s;
}

// Each broken set of particles, refused by the simulation, the tracer and the heat model alike.
TEST(LibraryInputs, ParticlesThatCannotBeSimulatedAreRefusedByName) {
  struct Case {
    std::function<void(Particles&)> spoil;
    const char* message;
  };
  const Case cases[] = {
      {[](Particles& p) { p.temperature.clear(); },
       "the arrays differ in length (3 centres, 3 "
       "radii, 3 materials, 0 temperatures"},
      {[](Particles& p) { p.centre.pop_back(); }, "the arrays differ in length (2 centres"},
      {[](Particles& p) { p.centre[1].x() = kNaN; }, "particle 1: its centre is not a finite"},
      {[](Particles& p) { p.radius[2] = -1e-4; }, "particle 2: radius r = -0.0001: must be > 0"},
      {[](Particles& p) { p.temperature[0] = -100; },
       "particle 0: temperature -100 K: must be > 0 and finite"},
      {[](Particles& p) { p.alive[2] = 7; }, "particle 2: live flag 7: must be 0 or 1"},
  };
  for (const Case& c : cases) {
    SCOPED_TRACE(c.message);
    Particles p = three_spheres();
    c.spoil(p);
    testing::expect_error<InputError>([&] { Simulation sim(one_pulse(), p); }, c.message);
    SimulationSpec from_file = one_pulse();  // particles a caller read from a file: checked too
    from_file.packing.source = "file";
    testing::expect_error<InputError>([&] { Simulation sim(from_file, p); }, c.message);
    testing::expect_error<InputError>([&] { Tracer tracer(p, OpticsSpec{}); }, c.message);
    testing::expect_error<InputError>([&] { ThermalModel model(p, {Material{}}, ThermalSpec{}); },
                                      c.message);
  }
  Particles p = three_spheres();
  testing::expect_error<InputError>([&] { p.remove(3); },
                                    "Particles::remove: particle 3 >= count 3");
}

// The simulation's own numbers: a negative or NaN step was read as one step per pulse, a
// negative period or stagger cap ran; a tiny duration is shown as itself (not 0.000000).
TEST(LibraryInputs, ASimulationSpecOutsideItsRangesIsRefusedByName) {
  struct Case {
    std::function<void(SimulationSpec&)> spoil;
    const char* message;
  };
  const Case cases[] = {
      {[](SimulationSpec& s) { s.dt = -1e-14; }, "`thermal.dt` = -1e-14: must be >= 0"},
      {[](SimulationSpec& s) { s.dt = kNaN; }, "`thermal.dt` = nan: must be >= 0"},
      {[](SimulationSpec& s) { s.pulses.period = -1; }, "`pulses.period` = -1: must be >= 0"},
      {[](SimulationSpec& s) { s.max_staggers = -1; }, "`thermal.max_staggers` = -1: must be >= 0"},
      {[](SimulationSpec& s) { s.pulses.duration = -1e-13; },
       "`pulses.duration` = -1e-13: must be > 0"},
      {[](SimulationSpec& s) { s.pulses.count = -2; }, "`pulses.count` = -2: must be >= 0"},
      // A default spec: the library has no "auto"; the refusal names what the run file's is.
      {[](SimulationSpec& s) { s.pulses = PulseSpec{}; },
       "`pulses.duration` = 0: must be > 0 and finite (the run file's \"auto\" is "
       "paper_time_step(xi, R), xi R / c: 5.42e-15 s for the paper's scene)"},
  };
  for (const Case& c : cases) {
    SimulationSpec s = one_pulse();
    c.spoil(s);
    testing::expect_error<InputError>([&] { Simulation sim(s, three_spheres()); }, c.message);
  }
}

// The limits beyond which the arithmetic breaks (conductivity 1e308 gave non-finite temperatures,
// latent bands 1e25 booked energies the beam never gave, thermal.dt = 1e308 s ran to a clock of
// inf) were the command line's alone: the library took them. They are the library's now, with the
// command line's messages.
TEST(LibraryInputs, ValuesBeyondWhatTheArithmeticHoldsAreRefusedByName) {
  struct Case {
    std::function<void(SimulationSpec&)> spoil;
    const char* message;
  };
  Wall wall;
  wall.axis = 2;
  const Case cases[] =
      {
          {[](SimulationSpec& s) { s.materials[0].conductivity = 1e308; },
           "material.conductivity = 1e+308: must be <= 1e+20 W/(m K)"},
          {[](SimulationSpec& s) { s.materials[0].c_liquid = 1e13; },
           "material.c_liquid = 1e+13: must be <= 1e+12 J/(kg K)"},
          {[](SimulationSpec& s) { s.materials[0].latent_melt = 1e25; },
           "material.latent_melt = 1e+25: must be <= 1e+12 J/(kg K) (a band's dP/dtheta"},
          {[](SimulationSpec& s) { s.materials[0].density = 1e15; },
           "material.density = 1e+15: must be <= 1e+12 kg/m^3"},
          {[](SimulationSpec& s) { s.materials[0].vapor_temperature = 1e300; },
           "material.vapor_temperature = 1e+300: must be <= 1e+12 K"},
          {[&](SimulationSpec& s) {
    s.thermal.walls = {wall};
    s.thermal.walls[0].temperature = 1e300;
           },
           "thermal.walls[0].temperature = 1e+300: must be <= 1e+12 K"},
          {[&](SimulationSpec& s) {
    s.thermal.walls = {wall};
    s.thermal.walls[0].conductance = 1e306;
           },
           "thermal.walls[0].conductance = 1e+306: must be <= 1e+20 W/K"},
             {[](SimulationSpec& s) { s.thermal.time_scaling = 1e290; },
              "thermal.time_scaling = 1e+290: must be <= 1e+12"},
             {[](SimulationSpec& s) { s.beam.power = 1e300; },
              "`beam.power` = 1e+300: must be <= 1e+20 W"},
             {[](SimulationSpec& s) { s.pulses.duration = 2e12; },
              "`pulses.duration` = 2e+12: must be <= 1e+12 s (30,000 years; far longer pulses"},
             {[](SimulationSpec& s) { s.pulses.period = 2e12; },
              "`pulses.period` = 2e+12: must be <= 1e+12 s (30,000 years; far longer steps"},
             {[](SimulationSpec& s) { s.dt = 2e12; },
              "`thermal.dt` = 2e+12: must be <= 1e+12 s (30,000 years; far longer steps"},
             };
  for (const Case& c : cases) {
    SimulationSpec s = one_pulse();
    c.spoil(s);
    testing::expect_error<InputError>([&] { Simulation sim(s, three_spheres()); }, c.message);
  }
  SimulationSpec at_limits = one_pulse();  // at the limits a run is taken
  at_limits.materials[0].conductivity = 1e20;
  at_limits.thermal.time_scaling = 1e12;
  at_limits.beam.power = 1e20;
  at_limits.pulses.duration = 1e12;
  at_limits.pulses.period = 1e12;
  at_limits.dt = 1e12;
  EXPECT_NO_THROW(Simulation(at_limits, three_spheres()));
}

// A beam made by hand: a direction that is not a unit vector (every ray escaped), an energy that
// is NaN (the ledger went NaN), particles added after the tracer took them (never hit, or a
// material it never checked).
TEST(LibraryInputs, AHandMadeLaunchIsRefusedByName) {
  const Particles p = three_spheres();
  const Beam beam = make_beam(BeamSpec{}, kD);
  std::vector<double> energies = beam.ray_energies(1e-13);
  {
    Tracer tracer(p, OpticsSpec{});
    Beam long_direction = beam;
    long_direction.direction = Vec3(3, 0, 0);
    testing::expect_error<InputError>(
        [&] { tracer.launch(long_direction, energies); },
        "launch: the beam's direction has |d| = 3: must be a unit vector");
    energies[5] = kNaN;
    testing::expect_error<InputError>([&] { tracer.launch(beam, energies); },
                                      "launch: ray 5's energy nan J: must be >= 0 and finite");
    energies[5] = -1.0;
    testing::expect_error<InputError>([&] { tracer.launch(beam, energies); },
                                      "ray 5's energy -1 J");
    EXPECT_EQ(tracer.ledger().injected, 0.0);  // nothing launched by the refused calls
  }
  Particles growing = three_spheres();
  Tracer tracer(growing, OpticsSpec{});
  growing.add(Vec3(0.5e-3, 0.5e-3, 0.9e-3), 1e-4);
  testing::expect_error<InputError>([&] { tracer.launch(beam, 1e-13); },
                                    "the particles were 3 when the tracer took them and are 4 now");
}

// The heat model's walls, matrices and stored heat are of the particles it took: one added later
// was read past their ends (valgrind: invalid reads in the assembly; 200,000 added: a non-finite
// temperature). Every call that reads them refuses, and a refused step changes nothing.
TEST(LibraryInputs, TheHeatModelRefusesParticlesAddedOrRemovedAfterItTookThem) {
  Material m;
  m.conductivity = 50;
  ThermalSpec walls;
  walls.walls.push_back(Wall{});
  Particles p = three_spheres();
  ThermalModel model(p, {m}, walls);
  model.set_contacts(find_contacts(p));
  const ThermalModel::Snapshot before = model.save();
  p.add(Vec3(0.5e-3, 0.5e-3, 0.9e-3), 1e-4);
  const std::vector<double> heat(p.size(), 1e-12);
  const std::string count = "the particles were 3 when the heat model took them and are 4 now";
  testing::expect_error<InputError>([&] { model.step(1e-12, heat); }, "thermal step: " + count);
  testing::expect_error<InputError>([&] { model.set_contacts({}); },
                                    "thermal set_contacts: " + count);
  testing::expect_error<InputError>([&] { model.restore(before); }, "thermal restore: " + count);
  testing::expect_error<InputError>([&] { (void)model.save(); }, "thermal save: " + count);
  testing::expect_error<InputError>([&] { (void)model.monotone_step_limit(); }, count);
  testing::expect_error<InputError>([&] { (void)model.component_of(0); }, count);
  p.temperature.pop_back(), p.centre.pop_back(), p.radius.pop_back(), p.material.pop_back();
  p.phase.pop_back(), p.alive.pop_back();
  EXPECT_EQ(model.ledger().absorbed, 0.0);  // the refused step took no heat
  EXPECT_NO_THROW(model.step(1e-12, std::vector<double>(3, 1e-12)));
  p.temperature.pop_back(), p.centre.pop_back(), p.radius.pop_back(), p.material.pop_back();
  p.phase.pop_back(), p.alive.pop_back();
  testing::expect_error<InputError>([&] { model.undo_step(); },
                                    "the particles were 3 when the heat model took them and are "
                                    "2 now");
}

// Contacts made by hand: a NaN area conducted nothing without a word, a distance of 0 gave "non-
// finite temperature" a step later. Each is refused by name, and the contacts before stay.
TEST(LibraryInputs, AHandMadeContactOrHeatIsRefusedByName) {
  Material m;
  m.conductivity = 50;
  Particles p = three_spheres();
  ThermalModel model(p, {m}, ThermalSpec{});
  const std::vector<Contact> found = find_contacts(p);
  ASSERT_FALSE(found.empty());
  model.set_contacts(found);
  const auto refused = [&](double area, double distance, const std::string& message) {
    testing::expect_error<InputError>(
        [&] {
      model.set_contacts({Contact{0, 2, area, distance}});
        },
        message);
    ASSERT_EQ(model.contacts().size(), found.size());
    EXPECT_EQ(model.contacts()[0].area, found[0].area);
  };
  refused(kNaN, 1e-4, "contact (0, 2): area nan m^2: must be finite and >= 0");
  refused(-1e-9, 1e-4, "contact (0, 2): area -1e-09 m^2: must be finite and >= 0");
  refused(1e-9, 0.0, "contact (0, 2): distance 0 m: must be finite and > 0");
  refused(1e-9, kNaN, "contact (0, 2): distance nan m: must be finite and > 0");
  refused(1e300, 1e-300, "contact (0, 2): conductance K A / d = inf W/K (area 1e+300 m^2");
  std::vector<double> heat(p.size(), 0.0);
  heat[1] = -1e-9;
  testing::expect_error<InputError>(
      [&] { model.step(1e-12, heat); },
      "thermal step: absorbed energy of particle 1 = -1e-09 J: must be finite and >= 0");
  heat[1] = kNaN;
  testing::expect_error<InputError>([&] { model.step(1e-12, heat); }, "particle 1 = nan J");
  EXPECT_EQ(model.ledger().absorbed, 0.0);
}

// The optics' tuning values: a Simulation picks chunk_rays itself but refuses one out of range
// (it took 0 and 100000 without a word), and spheres_per_primitive was clamped to [1, 64].
TEST(LibraryInputs, OpticsTuningOutOfRangeIsRefusedByName) {
  const auto refused = [](const std::function<void(OpticsSpec&)>& set, const std::string& message) {
    SimulationSpec spec = one_pulse();
    set(spec.optics);
    testing::expect_error<InputError>([&] { Simulation sim(spec, three_spheres()); }, message);
    const Particles p = three_spheres();
    testing::expect_error<InputError>([&] { Tracer tracer(p, spec.optics); }, message);
  };
  refused([](OpticsSpec& o) { o.chunk_rays = 0; },
          "OpticsSpec::chunk_rays = 0: must be in [1, 256]");
  refused([](OpticsSpec& o) { o.chunk_rays = 257; }, "OpticsSpec::chunk_rays = 257");
  refused([](OpticsSpec& o) { o.spheres_per_primitive = 0; },
          "OpticsSpec::spheres_per_primitive = 0: must be in [1, 64]");
  refused([](OpticsSpec& o) { o.spheres_per_primitive = 65; },
          "OpticsSpec::spheres_per_primitive = 65");
  SimulationSpec at_limits = one_pulse();
  at_limits.optics.chunk_rays = 1, at_limits.optics.spheres_per_primitive = 64;
  EXPECT_NO_THROW(Simulation(at_limits, three_spheres()));
  at_limits.optics.chunk_rays = 256, at_limits.optics.spheres_per_primitive = 1;
  EXPECT_NO_THROW(Simulation(at_limits, three_spheres()));
}

// A library caller's scene beyond the machine's memory is refused before the set-up allocates it,
// by name, as the command line's is: 10^9 rays (within beam.rays' range) ended in a bare
// std::bad_alloc part way into the set-up. Particles the caller gave are named as given.
TEST(LibraryInputs, ASceneBeyondTheMachinesMemoryIsRefusedByName) {
  if (machine_memory() > 3.9e11) GTEST_SKIP() << "a machine with more than 390 GB fits the scene";
  SimulationSpec many_rays = one_pulse();
  many_rays.beam.rays = 1'000'000'000;
  testing::expect_error<InputError>([&] { Simulation sim(many_rays, three_spheres()); },
                                    "`beam.rays` = 1000000000: the run needs at least 400 GB",
                                    "lower `beam.rays`");
  many_rays.packing.count = 3;
  testing::expect_error<InputError>([&] { Simulation sim(many_rays); },
                                    "`beam.rays` = 1000000000: the run needs at least 400 GB");
  constexpr double k24GiB = 24.0 * (1 << 30);
  testing::expect_error<InputError>(
      [&] { refuse_beyond_memory_of_given(one_pulse(), k24GiB, 100'000'000); },
      "the 100000000 particles given: the run needs at least 40 GB with `beam.rays` = 100",
      "; lower the particle count");
  EXPECT_NO_THROW(refuse_beyond_memory_of_given(one_pulse(), k24GiB, 10'000'000));
}

// A radius the user set through the spec is named in a thermal-mass refusal; particles the
// caller made are not blamed on spec.packing's keys, which did not make them.
TEST(LibraryInputs, OnlyTheSpecsOwnPackingIsNamedAsTheCauseOfARadius) {
  SimulationSpec s = one_pulse();
  s.materials[0].density = 1e-300;
  s.packing.count = 8;
  testing::expect_error<InputError>([&] { Simulation sim(s); },
                                    "from `packing.radius_ratio` = 0.325) has a");
  Particles mine;
  const double r = packing_radius(s.packing);  // the spec's radius, by the caller's hand
  mine.add(Vec3(0.5e-3, 0.5e-3, 0.5e-3), r);
  try {
    Simulation sim(s, mine);
    ADD_FAILURE() << "a thermal mass of 1e-300 kg/m^3 was accepted";
  } catch (const InputError& e) {
    EXPECT_NOT_CONTAINS(std::string(e.what()), "packing.radius_ratio") << e.what();
    EXPECT_CONTAINS(std::string(e.what()), "has a thermal mass") << e.what();
  }
}

// The thermal-mass check weighs the whole run's energy, every pulse's, not one pulse's (a step may
// gather several pulses, with a period shorter than thermal.dt): a particle that one pulse of 10 J
// warms by 1e307 K (a normal thermal mass of ~1e-306 J/K) the run's 100 pulses warm beyond the
// largest double. Refused as input, naming the keys behind the thermal mass and the run's 1000 J;
// a hundred times the density, or the one pulse alone, is taken.
TEST(LibraryInputs, AThermalMassIsCheckedAgainstEveryPulsesEnergy) {
  SimulationSpec s = one_pulse();
  s.beam.power = 1e13;  // 10 J a pulse of 1 ps
  s.pulses.duration = 1e-12;
  s.pulses.count = 100;
  const Particles p = three_spheres();
  double pulse = 0;  // summed as the simulation sums its rays' energies
  for (double e : make_beam(s.beam, kD).ray_energies(s.pulses.duration)) pulse += e;
  ASSERT_NEAR(pulse, 10.0, 1e-6);
  Material unit = s.materials[0];
  unit.density = 1;
  const double per_density = least_thermal_mass(unit, p.volume(0), s.thermal.time_scaling);
  // One pulse over the thermal mass is 1e307 K: finite, and the thermal mass a normal number.
  s.materials[0].density = pulse / (1e307 * per_density);
  const double mass = least_thermal_mass(s.materials[0], p.volume(0), s.thermal.time_scaling);
  ASSERT_GE(mass, std::numeric_limits<double>::min());
  ASSERT_TRUE(std::isfinite(pulse / mass));
  ASSERT_FALSE(std::isfinite(100 * pulse / mass));
  std::ostringstream run_energy;
  run_energy << "the run's " << pulse * 100 << " J warms by a finite amount";
  testing::expect_error<InputError>([&] { Simulation sim(s, p); },
                                    "particle 0 (radius 0.0001 m) has a thermal mass "
                                    "`material.density` x volume x min(`material.c_solid`, "
                                    "`material.c_liquid`) / `thermal.time_scaling`",
                                    "must be a finite normal number", run_energy.str());
  SimulationSpec one = s;  // the same particles under one pulse
  one.pulses.count = 1;
  EXPECT_NO_THROW(Simulation(one, p));
  s.materials[0].density *= 100;  // the run's 1000 J warm them by 1e307 K
  EXPECT_NO_THROW(Simulation(s, p));
}

}  // namespace
// What the command line warns of once a run is set up, a library caller reads from the simulation:
// particles placed away from the cube the beam is centred on, a wall out of their reach.
TEST(LibraryInputs, AMisplacedSceneIsSaidToTheCaller) {
  SimulationSpec spec = one_pulse();
  EXPECT_TRUE(Simulation(spec, three_spheres()).scene_warnings().empty());
  Particles far = three_spheres();
  for (Vec3& c : far.centre) c += Vec3(0, 5e-3, 0);  // beside the cube [0, 1 mm]^3
  const std::vector<std::string> beside = Simulation(spec, far).scene_warnings();
  ASSERT_EQ(beside.size(), 1u);
  EXPECT_CONTAINS(beside[0], "meets no particle");
  Wall wall;
  wall.axis = 2;
  wall.position = kD;  // z+: the spheres reach 0.6 mm of the 1 mm cube
  wall.reach = 1e-5;
  spec.thermal.walls = {wall};
  const std::vector<std::string> lonely = Simulation(spec, three_spheres()).scene_warnings();
  ASSERT_EQ(lonely.size(), 1u);
  EXPECT_CONTAINS(lonely[0], "the wall z+ (`thermal.walls`) touches no particle");
  // A bed of 1 cm spheres under the 1 mm default cube: the 0.3 mm beam meets one of them.
  spec.thermal.walls.clear();
  Particles large;
  large.add(Vec3(5e-4, 5e-4, 5e-4), 1e-2);
  large.add(Vec3(2.5e-2, 5e-4, 5e-4), 1e-2);
  // The caller's particles are judged whatever packing.source says (a library review read a DEM
  // file in code, left the source at its default, and heard nothing); generated ones are not.
  for (const char* source : {"random-overlap", "file"}) {
    spec.packing.source = source;
    const std::vector<std::string> outgrown = Simulation(spec, large).scene_warnings();
    ASSERT_EQ(outgrown.size(), 1u) << source;
    EXPECT_CONTAINS(outgrown[0],
                    "the beam is 0.0003 m wide (`beam.diameter_fraction` = 0.3 x `sample.size` = "
                    "0.001 m), narrower than the particles (median diameter 0.02 m)");
  }
  // Eight generated spheres are wider than the beam by design (R = 0.325 D / 2): not judged.
  SimulationSpec few = spec;
  few.packing.source = "random-overlap";
  few.packing.count = 8;
  EXPECT_TRUE(Simulation(few).scene_warnings().empty());
  spec.pulses.count = 0;  // no beam: the cube places nothing the particles miss
  EXPECT_TRUE(Simulation(spec, large).scene_warnings().empty());
}

// One stray sphere far from a bed (a DEM particle that flew off) stretches the particles' box,
// where the rays end, and so every pulse's flight and "pulse" step: a library review's 1 m stray
// took the bed's peak from 624 K to 323 K without a word. Said, with the gap and the groups;
// a stray just beside the bed, or one that went (dead), is not.
TEST(LibraryInputs, AStrayParticleFarFromTheBedIsSaidToTheCaller) {
  SimulationSpec spec = one_pulse();
  Particles bed;
  for (int i = 0; i < 5; ++i)
    for (int j = 0; j < 5; ++j)
      for (int k = 0; k < 5; ++k)
        bed.add(Vec3(1e-4 + 2e-4 * i, 1e-4 + 2e-4 * j, 1e-4 + 2e-4 * k), 1.1e-4);
  EXPECT_TRUE(Simulation(spec, bed).scene_warnings().empty());
  const auto with_stray = [&](const Vec3& at, bool alive = true) {
    Particles p = bed;
    p.add(at, 5e-6);
    p.alive.back() = alive;
    return Simulation(spec, p).scene_warnings();
  };
  const std::vector<std::string> far = with_stray(Vec3(1e-3, 5e-4, 1.0));
  ASSERT_EQ(far.size(), 1u);
  EXPECT_CONTAINS(far[0], "the particles lie in two groups far apart: along z an empty gap of ");
  EXPECT_CONTAINS(far[0], "separates 125 of them from 1, and they span 1.00002 m");
  EXPECT_CONTAINS(far[0], "each pulse's flight, the \"pulse\" step and the \"auto\" period grow");
  const std::vector<std::string> below = with_stray(Vec3(-2e-2, 5e-4, 5e-4));
  ASSERT_EQ(below.size(), 1u);
  EXPECT_CONTAINS(below[0], "along x an empty gap of ");
  EXPECT_CONTAINS(below[0], "separates 1 of them from 125");
  EXPECT_TRUE(with_stray(Vec3(1.9e-3, 5e-4, 5e-4)).empty());  // a gap narrower than the bed
  EXPECT_TRUE(with_stray(Vec3(1e-3, 5e-4, 1.0), false).empty());
  spec.pulses.count = 0;  // no rays: no flight to stretch
  EXPECT_TRUE(Simulation(
                  spec,
                  [&] {
    Particles p = bed;
    p.add(Vec3(1e-3, 5e-4, 1.0), 5e-6);
    return p;
                  }())
                  .scene_warnings()
                  .empty());
}

using testing::quick_scene;

// A particle passed in dead left before the run: its temperature is not the run's peak (one at
// 5000 K was, before any step); with every particle dead there is no peak at all.
TEST(LibraryInputs, ParticlesPassedInDeadSetNoPeak) {
  SimulationSpec spec = one_pulse();
  spec.pulses.count = 0;
  Particles p = three_spheres();
  p.alive[1] = 0;
  p.temperature[1] = 5000;
  EXPECT_EQ(Simulation(spec, p).figures().max_temperature, std::optional<double>(300.0));
  for (std::size_t i = 0; i < p.size(); ++i) p.alive[i] = 0;
  EXPECT_FALSE(Simulation(spec, p).figures().max_temperature.has_value());
}

// The paper's ray time step, xi R / c: 5.4e-15 s for its scene (R = 0.325 (D^3 / 1000)^(1/3)
// = 32.5 um, xi = 0.05), as README's Table 1 notes say.
TEST(LibraryInputs, ThePapersRayTimeStepIsXiRoverC) {
  EXPECT_DOUBLE_EQ(paper_time_step(0.05, 3.25e-5), 0.05 * 3.25e-5 / 2.99792458e8);
  EXPECT_NEAR(paper_time_step(0.05, 3.25e-5), 5.4e-15, 0.05e-15);
}

// The warnings of `run_warnings()` after a run of `spec`.
std::vector<std::string> warnings_of_run(const SimulationSpec& spec) {
  Simulation sim(spec);
  sim.run();
  return sim.run_warnings();
}

// What the command line warns of at a run's end, a library caller reads from the simulation: the
// judgement of a run's physics is the library's, and the CLI only prints it. The scenes are the
// CLI tests' of each warning.
TEST(LibraryInputs, ARunSaysWhereItsResultsAreInDoubt) {
  SimulationSpec spec = quick_scene();
  {
    Simulation sim(spec);
    EXPECT_TRUE(sim.run_warnings().empty());  // no step yet
    sim.run();
    EXPECT_TRUE(sim.run_warnings().empty()) << sim.run_warnings().front();
  }
  // Pulses of period 10 ps in steps of 3 ps start up to 2 ps late (the CLI's
  // PulsesStartAtTheirPeriodAndLateStartsAreAnnounced).
  spec.pulses.period = 1e-11;
  spec.dt = 3e-12;
  const std::vector<std::string> late = warnings_of_run(spec);
  ASSERT_EQ(late.size(), 1u);
  EXPECT_CONTAINS(late[0],
                  "3 of 5 pulses started more than 1% of `pulses.period` = 1e-11 s after "
                  "k x period (up to 2e-12 s late)");
  EXPECT_CONTAINS(late[0], "`thermal.dt` does not divide the period");
  spec.dt = 1e-12;
  EXPECT_TRUE(warnings_of_run(spec).empty());
  // A stagger of one redo, in the paper's scene with a liquid index of 3 that reflects far more
  // than the solid's 1.4 (the CLI's StaggerCyclesStopTheSameWayWhateverTheCap).
  spec = SimulationSpec{};
  spec.packing.count = 1000;
  spec.packing.seed = spec.beam.seed = 2013;
  spec.pulses.duration = 3e-13;
  spec.optics.materials[0].n_liquid = 3;
  spec.max_staggers = 1;
  const std::vector<std::string> staggers = warnings_of_run(spec);
  ASSERT_EQ(staggers.size(), 1u);
  EXPECT_CONTAINS(staggers[0],
                  "reached `thermal.max_staggers` = 1 redos with the optics still "
                  "changing: their result is the last redo's and depends on the cap");
  // A beam of 2e13 W heats by ~4e11 K, where the solves' 1e-10 of a step's change is ~40 K of
  // the 100 K between melting and vaporising (README, "Keys without a natural bound").
  spec = quick_scene();
  spec.beam.power = 2e13;
  const std::vector<std::string> hot = warnings_of_run(spec);
  ASSERT_EQ(hot.size(), 1u);
  EXPECT_CONTAINS(hot[0], "may misplace a particle beside the hottest by ~");
  // A fixed-point iteration held to 0.1 leaves particles below the 300 K they started at, in a
  // run that only heats.
  spec = quick_scene();
  spec.materials[0].conductivity = 100;
  spec.thermal.solver = "fixed-point";
  spec.thermal.tolerance = 0.1;
  const std::vector<std::string> loose = warnings_of_run(spec);
  ASSERT_FALSE(loose.empty());
  EXPECT_CONTAINS(loose.back(), "ended below 300 K, the least of the starting and wall");
}

// pulses.duration sets a pulse's energy, delivered within the rays' flight (MODEL.md section 5):
// pulses of 1 ns whose rays flew ~4e-12 s each are flashes, and the run says so; the same pulses
// a period of 1 ns apart are not, whatever their count; a duration of three periods is; a run
// stopped part way says nothing (its time so far is no pulse's whole share).
TEST(LibraryInputs, PulsesLongerThanTheTimeTheyHadAreSaidToBeFlashes) {
  SimulationSpec spec = quick_scene();
  spec.pulses.duration = 1e-9;
  const std::vector<std::string> flashes = warnings_of_run(spec);
  ASSERT_EQ(flashes.size(), 1u);
  EXPECT_CONTAINS(flashes[0],
                  "`pulses.duration` = 1e-09 s sets each pulse's energy (`beam.power` x "
                  "duration = 6e-06 J), which its rays deliver within their flight");
  EXPECT_CONTAINS(flashes[0], "(its rays' mean flight, with `pulses.period` = \"auto\")");
  spec.pulses.period = 1e-9;
  for (const int count : {1, 2, 5}) {
    spec.pulses.count = count;
    const std::vector<std::string> spaced = warnings_of_run(spec);
    EXPECT_TRUE(spaced.empty()) << count << ": " << spaced.front();
  }
  spec.pulses.duration = 3e-9;
  const std::vector<std::string> overlapping = warnings_of_run(spec);
  ASSERT_EQ(overlapping.size(), 1u);
  EXPECT_CONTAINS(overlapping[0],
                  "each pulse had 1e-09 s (`pulses.period`) before the next, so the heat saw "
                  "1.8e+04 W on average, 3 times `beam.power` = 6000 W; a duration longer than "
                  "the period adds energy, not time");
  spec.pulses.period = 0;
  Simulation part(spec);
  part.step();
  EXPECT_FALSE(part.done());
  EXPECT_TRUE(part.run_warnings().empty()) << part.run_warnings().front();
}

// A band one pass adds pushes a neighbour across another (ThermalPhase's
// ACorrectorStoppedAtItsCapWithANewBandSaysSo): a liquid sphere at 640 K touching a solid one at
// 510 K, a step of 4 ms that equalises them, under a faint pulse. With one corrector pass the step
// stops with the new band unsolved, and the run says so; with the default four it does not.
TEST(LibraryInputs, ALatentHeatCorrectionCutShortIsSaidToTheCaller) {
  SimulationSpec spec;
  spec.packing.sample_size = kD;
  spec.beam.rays = 100;
  spec.beam.power = 0.1;  // W: a faint beam, that warms the pair by ~1 mK
  spec.pulses.count = 1;
  spec.pulses.duration = 1e-13;
  spec.materials[0].conductivity = 1;
  spec.dt = 4e-3;
  Particles pair;
  pair.add(Vec3(5e-4, 5e-4, 5e-4), 1e-4, 0, 640.0);
  pair.add(Vec3(6.5e-4, 5e-4, 5e-4), 1e-4, 0, 510.0);
  for (const int cap : {1, 4}) {
    spec.thermal.max_phase_corrections = cap;
    Simulation sim(spec, pair);
    sim.run();
    ASSERT_EQ(sim.counts().capped_phase_steps, cap == 1 ? 1u : 0u) << cap;
    const std::vector<std::string> said = sim.run_warnings();
    // Either way the liquid sphere was charged its solidification band and stayed liquid: more
    // heat than the faint pulse brought
    // (Cli.LatentHeatChargedWithoutACrossingIsCountedAndWarnedOf).
    ASSERT_FALSE(said.empty());
    EXPECT_TRUE(said.back().find("J of latent heat was charged in 1 particle (sub-)steps") !=
                std::string::npos)
        << said.back();
    if (cap == 4) {
      EXPECT_EQ(said.size(), 1u) << said.front();
      continue;
    }
    ASSERT_EQ(said.size(), 2u);
    EXPECT_EQ(said[0],
              "1 heat steps stopped the latent-heat correction at its cap of 1 passes while a "
              "particle still crossed a new band (theta_m or theta_v): that band's latent heat "
              "is missing from the step; a shorter `thermal.dt` crosses fewer bands per step");
  }
}

// Spheres of 1e6 m (the largest radius a packing file may give) warm by less than doubles hold:
// the heat ledger stays open, and the run says so (the CLI's
// NumbersBeyondTheArithmeticAreRefusedAndTheLimitsRun).
TEST(LibraryInputs, AnOpenLedgerIsSaidToTheCaller) {
  SimulationSpec spec = quick_scene();
  Particles giants;
  giants.add(Vec3(5e-4, 5e-4, 5e-4), 1e6);
  giants.add(Vec3(3e-4, 3e-4, 3e-4), 1e6);
  Simulation sim(spec, giants);
  sim.run();
  const std::vector<std::string> said = sim.run_warnings();
  ASSERT_EQ(said.size(), 1u);
  EXPECT_CONTAINS(said[0], "the heat ledger is open by");
}

// What the spec alone warns of, before any set-up (the CLI prints it before it sets up).
TEST(LibraryInputs, ASpecSaysWhatItsRunWillNotDoWell) {
  SimulationSpec spec = quick_scene();
  EXPECT_TRUE(spec_warnings(spec).empty());
  spec.dt = 1e-20;
  const std::vector<std::string> tiny = spec_warnings(spec);
  ASSERT_EQ(tiny.size(), 1u);
  EXPECT_CONTAINS(tiny[0],
                  "`thermal.dt` = 1e-20 s: light crosses the sample (0.001 m) in 3.34e-12 "
                  "s, 3.34e+08 steps of this length per crossing");
  spec = quick_scene();
  spec.materials[0].conductivity = 0;
  Wall wall;
  wall.axis = 2;
  wall.position = 0;
  wall.conductance = -1;  // pi K R
  spec.thermal.walls = {wall};
  const std::vector<std::string> walls = spec_warnings(spec);
  ASSERT_EQ(walls.size(), 1u);
  EXPECT_CONTAINS(walls[0], "the walls take no heat");
  // A bed at its melting temperature starts liquid, and its melted fraction counts it; a kelvin
  // below, it starts solid and nothing is said.
  spec = quick_scene();
  spec.packing.initial_temperature = spec.materials[0].melt_temperature;
  const std::vector<std::string> molten = spec_warnings(spec);
  ASSERT_EQ(molten.size(), 1u);
  EXPECT_CONTAINS(molten[0],
                  "`material.initial_temperature` = 600 K is at or above "
                  "`material.melt_temperature` = 600 K: its particles start liquid");
  Simulation sim(spec);
  EXPECT_EQ(sim.figures().melted_fraction, 1.0);
  spec.packing.initial_temperature -= 1;
  EXPECT_TRUE(spec_warnings(spec).empty());
}

// The quick scene, conducting, with one of its times far beyond its cap: each was the command
// line's to refuse, and a library caller's ran. Refused as the run file's value is, by its key.
TEST(LibraryInputs, TimesBeyondTheirCapsAreRefusedByName) {
  const std::function<void(SimulationSpec&)> spoils[] = {
      [](SimulationSpec& s) { s.pulses.duration = 1e300; },
      [](SimulationSpec& s) { s.pulses.period = 1e300; },
      [](SimulationSpec& s) { s.dt = 1e300; },
  };
  const char* keys[] = {"`pulses.duration` = 1e+300: must be <= 1e+12 s",
                        "`pulses.period` = 1e+300: must be <= 1e+12 s",
                        "`thermal.dt` = 1e+300: must be <= 1e+12 s"};
  for (int k = 0; k < 3; ++k) {
    SimulationSpec spec = quick_scene();
    spoils[k](spec);
    testing::expect_error<InputError>([&] { Simulation sim(spec); }, keys[k]);
  }
  // A step so short that the run would never end (3.3e18 steps per light crossing of 1 mm) is
  // refused as the run file's is; 1e9 steps per crossing is the limit.
  SimulationSpec spec = quick_scene();
  spec.dt = 1e-30;
  testing::expect_error<InputError>(
      [&] { Simulation sim(spec); },
      "`thermal.dt` = 1e-30: must be >= sample.size / c / 1e9 = 3.33564e-21 s (light crosses "
      "the sample in 3.33564e-12 s)");
  spec.dt = 1e-3 / kSpeedOfLight / kMaxStepsPerCrossing;
  Simulation at_limit(spec);  // accepted (and not run: 1e9 steps)
}

}  // namespace beampack

namespace beampack {
namespace {

// A library review's findings: each misuse ran on and crashed or answered wrongly in silence.

SimulationSpec conducting_pulses(int pulses) {
  SimulationSpec s = one_pulse();
  s.pulses.count = pulses;
  s.materials[0].conductivity = 100.0;
  return s;
}

// The state of a simulation of `spec` over `p` after one step.
std::string state_after_one_step(const SimulationSpec& spec, const Particles& p) {
  Simulation first(spec, p);
  first.step();
  StateWriter written;
  first.write_state(written);
  return written.finish();
}

// Particles a run removed stay out of its ray scene: a state restored into a simulation that has
// stepped brought them back to life for the heat and not for the rays (absorbed 4.5e-9 J where
// the run absorbs 1.6e-8 J, the ledger closed).
TEST(LibraryMisuse, AStateIsRestoredOnlyIntoAFreshSimulation) {
  const SimulationSpec spec = conducting_pulses(3);
  const Particles p = random_overlap_packing(200, kD, 0.325, 7);
  const std::string bytes = state_after_one_step(spec, p);
  Simulation stepped(spec, p);
  stepped.step();
  StateReader in(bytes, "state");
  testing::expect_error<InputError>([&] { stepped.read_state(in); }, "has taken 1 steps",
                                    "into a new Simulation");
  Simulation fresh(spec, p);
  StateReader again(bytes, "state");
  fresh.read_state(again);  // the documented use
  EXPECT_TRUE(fresh.step());
}

// A state holds no spec: one of a polarised beam read into a simulation of an unpolarised one is
// refused before it changes anything (it restored the clock, counts and particles, then threw at
// the rays, and the simulation stepped on from that mixture), so the simulation runs as it would
// have without the attempt.
TEST(LibraryMisuse, AStateRefusedChangesNothing) {
  SimulationSpec polarised = conducting_pulses(3);
  polarised.optics.polarisation.linear = true;
  const Particles p = random_overlap_packing(200, kD, 0.325, 7);
  const std::string bytes = state_after_one_step(polarised, p);
  const SimulationSpec spec = conducting_pulses(3);
  Simulation tried(spec, p), untried(spec, p);
  StateReader in(bytes, "state");
  testing::expect_error<InputError>([&] { tried.read_state(in); }, "checkpoint: the state's rays",
                                    "polarised and this tracer's are not");
  tried.run();
  untried.run();
  EXPECT_EQ(tried.figures().time, untried.figures().time);
  EXPECT_EQ(tried.particles().temperature, untried.particles().temperature);
  EXPECT_EQ(tried.absorbed(), untried.absorbed());
}

// README: a particle passed in dead counts as vaporised. Its phase decided: left solid it counted
// as nothing, left liquid as melted.
TEST(LibraryMisuse, ParticlesPassedInDeadAreVaporised) {
  Particles p = random_overlap_packing(200, kD, 0.325, 7);
  for (std::size_t i = 0; i < 50; ++i) {
    p.alive[i] = 0;
    p.phase[i] = i % 2 ? Phase::solid : Phase::liquid;
  }
  SimulationSpec spec = one_pulse();
  spec.pulses.count = 0;
  const Simulation sim(spec, p);
  EXPECT_NEAR(sim.figures().vaporized_fraction, 0.25, 1e-14);  // equal spheres: a quarter
  EXPECT_EQ(sim.figures().melted_fraction, 0.0);
}

// Volume fractions of equal spheres are k / N to the bit: plain sums gave 6 of 200 vaporised as
// 0.029999999999999884 (17 ulps) in summary.json beside particles.csv's 6 rows, and the quotient
// of the compensated sums' values 60 of 1000 as 0.060000000000000005.
TEST(LibraryInputs, FractionsOfEqualSpheresAreTheirCountsShare) {
  const Particles all = random_overlap_packing(200, kD, 0.325, 7);
  SimulationSpec spec = one_pulse();
  spec.pulses.count = 0;
  for (std::size_t k = 1; k <= all.size(); ++k) {
    Particles p = all;
    for (std::size_t i = 0; i < k; ++i) p.alive[i] = 0;
    const double share = double(k) / double(all.size());
    EXPECT_EQ(Simulation(spec, p).figures().vaporized_fraction, share) << k << " of " << all.size();
  }
}

// The fractions to the bit, for spheres of many sizes: each phase's volumes as a compensated sum in
// particle order, over the whole volume summed the same way, divided as compensated sums
// (summary.json and history.csv print all 17 digits, so an order or a rounding changed is a
// changed output).
TEST(LibraryInputs, FractionsAreCompensatedSumsInParticleOrder) {
  Particles p = random_overlap_packing(30000, kD, 0.325, 11);
  for (std::size_t i = 0; i < p.size(); ++i) {
    p.radius[i] *= 0.5 + double((i * 7919) % 1000) / 999.0;
    if (i % 3 == 0) p.alive[i] = 0;          // vaporised
    if (i % 3 == 1) p.temperature[i] = 650;  // liquid: between theta_m and theta_v
  }
  CompensatedSum all, vapor, liquid;
  for (std::size_t i = 0; i < p.size(); ++i) {
    all.add(p.volume(i));
    if (i % 3 == 0) vapor.add(p.volume(i));
    if (i % 3 == 1) liquid.add(p.volume(i));
  }
  SimulationSpec spec = one_pulse();
  spec.pulses.count = 0;
  const Figures f = Simulation(spec, p).figures();
  EXPECT_EQ(f.vaporized_fraction, compensated_ratio(vapor, all));
  EXPECT_EQ(f.melted_fraction, compensated_ratio(liquid, all));
}

// The division behind the fractions: k of N equal volumes is k / N, to the bit, for every k and
// sphere size, where the quotient of the two sums' rounded values is an ulp off for some.
TEST(LibraryInputs, CompensatedRatioOfEqualVolumesIsTheCountsRatio) {
  int off_before = 0;
  for (const double radius : {3.25e-5, 1.7e-6, 4.1e-4}) {
    const std::size_t n = 1000;
    CompensatedSum all, vapor;
    for (std::size_t i = 0; i < n; ++i)
      all.add(4.0 / 3.0 * std::numbers::pi * radius * radius * radius);
    for (std::size_t k = 0; k <= n; k += 1) {
      if (k > 0) vapor.add(4.0 / 3.0 * std::numbers::pi * radius * radius * radius);
      const double exact = double(k) / double(n);
      off_before += vapor.value() / all.value() != exact;
      ASSERT_EQ(compensated_ratio(vapor, all), exact) << radius << " " << k;
    }
  }
  EXPECT_GT(off_before, 0);  // the plain quotient is off for some: the test can tell them apart
}

// Embree asserted on the invalid float rays and aborted the process.
TEST(LibraryMisuse, ABeamStartingNowhereIsRefused) {
  const Particles p = three_spheres();
  const Beam beam = make_beam(BeamSpec{}, kD);
  Tracer tracer(p, OpticsSpec{});
  Beam nan_origin = beam;
  nan_origin.origin[5].x() = kNaN;
  testing::expect_error<InputError>([&] { tracer.launch(nan_origin, 1e-13); },
                                    "launch: ray 5's origin (nan", "must be finite");
  Beam far = beam;
  for (Vec3& o : far.origin) o.x() -= 1e300;
  testing::expect_error<InputError>([&] { tracer.launch(far, 1e-13); }, "ray 0's origin (-1e+300");
  Beam nan_centre = beam;
  nan_centre.centre.y() = kNaN;
  testing::expect_error<InputError>([&] { tracer.launch(nan_centre, 1e-13); }, "the beam's centre");
  EXPECT_EQ(tracer.ledger().injected, 0.0);
  tracer.launch(beam, 1e-13);  // the tracer still works
  EXPECT_GT(tracer.ledger().injected, 0.0);
}

// A state from a tracer on 5000 particles advanced in one on 50 indexed past its particles
// (a segmentation fault); a NaN energy made the ledger NaN.
TEST(LibraryMisuse, ARestoredRayStateIsChecked) {
  const Beam beam = make_beam(BeamSpec{}, kD);
  const Particles big = random_overlap_packing(5000, kD, 0.325, 7);
  Tracer large(big, OpticsSpec{});
  large.launch(beam, 1e-13);
  const RayState state = large.save();
  const Particles small = random_overlap_packing(50, kD, 0.325, 7);
  Tracer tracer(small, OpticsSpec{});
  testing::expect_error<InputError>([&] { tracer.restore(state); }, "restore: ray",
                                    "beyond the 50 particles");
  RayState nan_energy = state;
  nan_energy.energy[3] = kNaN;
  Tracer same(big, OpticsSpec{});
  testing::expect_error<InputError>([&] { same.restore(nan_energy); }, "restore: ray 3 has energy");
  RayState short_array = state;
  short_array.t_next.pop_back();
  testing::expect_error<InputError>(
      [&] { same.restore(short_array); },
      "a per-ray array holds " + std::to_string(state.live.size() - 1));
  same.restore(state);  // the state itself is fine
  EXPECT_EQ(same.save().live_count, state.live_count);
}

// launch refused a changed particle count; advance did not, and stepped rays into freed memory.
TEST(LibraryMisuse, AdvanceRefusesParticlesThatChangedCount) {
  Particles p = three_spheres();
  Tracer tracer(p, OpticsSpec{});
  std::vector<double> deposits;
  tracer.launch(make_beam(BeamSpec{}, kD), 1e-13);
  p = Particles{};
  testing::expect_error<InputError>(
      [&] { tracer.advance(std::numeric_limits<double>::infinity(), deposits); },
      "advance: the particles were 3 when the tracer took them and are 0 now");
}

// A step that threw had traced its rays and not conducted their heat; the next step() launched
// the next pulse on top, and three tries later the run was "done" at 300 K with an open ledger.
TEST(LibraryMisuse, AfterAFailedStepTheSimulationRefusesToGoOn) {
  SimulationSpec spec = conducting_pulses(3);
  spec.thermal.solver = "fixed-point";
  spec.thermal.max_iterations = 2;
  Simulation sim(spec, random_overlap_packing(200, kD, 0.325, 7));
  const std::string first = testing::error_message<RunError>([&] { sim.step(); });
  ASSERT_NE(first, testing::kAccepted);
  testing::expect_error<RunError>([&] { sim.step(); }, "an earlier step failed (", first,
                                  "cannot go on");
  EXPECT_EQ(sim.pulses_launched(), 1);  // no pulse launched on top of the failed step
  StateWriter out;  // nor is its half-stepped state saved, to be resumed as if whole
  testing::expect_error<RunError>([&] { sim.write_state(out); },
                                  "write_state: this simulation "
                                  "failed (",
                                  first);
}

// on_pulse_end runs inside a step: a step() from it launched the same pulse again and called it
// again, until the stack ran out. Refused by name; a callback that catches the refusal leaves the
// run as it would be without the attempt.
TEST(LibraryMisuse, ACallbackCannotStepItsOwnSimulation) {
  const SimulationSpec spec = conducting_pulses(3);
  const Particles p = random_overlap_packing(200, kD, 0.325, 7);
  for (const bool by_run : {false, true}) {
    SCOPED_TRACE(by_run ? "run() in the callback" : "step() in the callback");
    Simulation sim(spec, p);
    int depth = 0;  // without the refusal: a clean failure instead of a stack overflow
    sim.on_pulse_end([&](int) {
      if (++depth > 3) throw std::logic_error("on_pulse_end re-entered its own step");
      if (by_run) sim.run();
      else sim.step();
    });
    testing::expect_error<InputError>(
        [&] { sim.run(); }, "step: called from inside this simulation's on_pulse_end callback",
        "a simulation cannot be stepped from its own callback");
    EXPECT_EQ(depth, 1);
  }
  Simulation plain(spec, p);
  plain.run();
  Simulation caught(spec, p);
  int refused = 0;
  caught.on_pulse_end([&](int) {
    try {
      caught.step();
    } catch (const InputError&) {
      ++refused;
    }
  });
  caught.run();
  EXPECT_EQ(refused, 3);
  EXPECT_EQ(caught.particles().temperature, plain.particles().temperature);
  EXPECT_EQ(caught.figures().energy.absorbed, plain.figures().energy.absorbed);
  EXPECT_FALSE(caught.step());  // done, and stepping again after the callbacks is allowed
}

// A callback's own error (a full disk while it writes) reaches the caller, and the simulation
// stays whole: the next step() calls the callback again for the same pulse and the run goes on
// to the numbers of a run without the error. Before, every later step() threw "an earlier step
// failed (...), leaving its rays traced and its heat not", which was not so.
TEST(LibraryMisuse, ACallbackThatThrowsLeavesTheSimulationWhole) {
  const SimulationSpec spec = conducting_pulses(3);
  const Particles p = random_overlap_packing(200, kD, 0.325, 7);
  Simulation plain(spec, p);
  plain.run();
  Simulation sim(spec, p);
  std::vector<int> calls;
  bool fail_once = true;
  sim.on_pulse_end([&](int pulse) {
    calls.push_back(pulse);
    if (pulse == 1 && std::exchange(fail_once, false)) throw std::runtime_error("disk full");
  });
  testing::expect_error<std::runtime_error>([&] { sim.run(); }, "disk full");
  sim.run();
  EXPECT_EQ(calls, (std::vector<int>{0, 1, 1, 2}));
  EXPECT_EQ(sim.particles().temperature, plain.particles().temperature);
  EXPECT_EQ(sim.figures().energy.absorbed, plain.figures().energy.absorbed);
  EXPECT_EQ(sim.counts().steps, plain.counts().steps);
}

}  // namespace
}  // namespace beampack
