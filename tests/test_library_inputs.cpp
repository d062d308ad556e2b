// A library caller's inputs are checked as the run file's are: particles, the simulation's own
// numbers and a hand-made launch are refused by name (InputError), never a crash, a NaN ledger
// or a silent reading (a library review found each of these running).
#include <gtest/gtest.h>

#include <cmath>
#include <functional>
#include <limits>
#include <string>
#include <vector>

#include "engine/beam.h"
#include "engine/simulation.h"
#include "engine/tracer.h"
#include "geometry/error.h"
#include "geometry/packing.h"
#include "tests/expect_error.h"
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
  };
  for (const Case& c : cases) {
    SimulationSpec s = one_pulse();
    c.spoil(s);
    testing::expect_error<InputError>([&] { Simulation sim(s, three_spheres()); }, c.message);
  }
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
    EXPECT_EQ(std::string(e.what()).find("packing.radius_ratio"), std::string::npos) << e.what();
    EXPECT_NE(std::string(e.what()).find("has a thermal mass"), std::string::npos) << e.what();
  }
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
  EXPECT_NE(beside[0].find("meets no particle"), std::string::npos) << beside[0];
  Wall wall;
  wall.axis = 2;
  wall.position = kD;  // z+: the spheres reach 0.6 mm of the 1 mm cube
  wall.reach = 1e-5;
  spec.thermal.walls = {wall};
  const std::vector<std::string> lonely = Simulation(spec, three_spheres()).scene_warnings();
  ASSERT_EQ(lonely.size(), 1u);
  EXPECT_NE(lonely[0].find("the wall z+ (`thermal.walls`) touches no particle"), std::string::npos)
      << lonely[0];
}

}  // namespace beampack
