// Stiff steps: dt = 1e6 x the explicit limit. Backward Euler keeps the discrete maximum principle;
// explicit steps beyond the limit are sub-stepped or refused; the fixed-point iteration fails loudly.
#include <gtest/gtest.h>

#include <algorithm>
#include <random>

#include "geometry/contact.h"
#include "geometry/error.h"
#include "geometry/packing.h"
#include "tests/thermal_test_util.h"
#include "thermal/thermal_model.h"

namespace beampack {
namespace {

// The paper's packing at 400 particles, K = 100, temperatures uniform in [300, 500] K.
Particles stiff_packing() {
  Particles p = random_overlap_packing(400, 1e-3, 0.45, 7);
  std::mt19937_64 rng(11);
  std::uniform_real_distribution<double> u(300.0, 500.0);
  for (double& t : p.temperature) t = u(rng);
  return p;
}

Material conductive() {
  Material m;
  m.conductivity = 100;
  m.melt_temperature = 1e4;  // no phase change in these tests
  m.vapor_temperature = 2e4;
  return m;
}

double explicit_limit(Particles& p) {
  ThermalSpec spec;
  spec.phi = 0;
  ThermalModel model(p, {conductive()}, spec);
  model.set_contacts(find_contacts(p));
  return model.monotone_step_limit();
}

class StiffImplicit : public ::testing::TestWithParam<const char*> {};

TEST_P(StiffImplicit, BackwardEulerBoundedAndMonotone) {
  Particles p = stiff_packing();
  const double dt = 1e6 * explicit_limit(p);
  ThermalSpec spec;
  spec.phi = 1;
  spec.solver = GetParam();
  spec.tolerance = 1e-12;
  spec.max_iterations = 100000;  // CG needs ~sqrt(condition) ~ 1e3+ iterations here
  ThermalModel model(p, {conductive()}, spec);
  model.set_contacts(find_contacts(p));
  double heat = 0;  // heat content sum c_i theta_i, the scale of the ledger's round-off
  for (std::size_t i = 0; i < p.size(); ++i) heat += model.thermal_mass(i) * p.temperature[i];
  double lo = *std::min_element(p.temperature.begin(), p.temperature.end());
  double hi = *std::max_element(p.temperature.begin(), p.temperature.end());
  const double lo0 = lo, hi0 = hi;
  // The solver's own error on this system (condition ~1e6) is far below this; the max principle
  // is exact for the exact solution of an M-matrix system.
  const double slack = 1e-6;
  for (int s = 0; s < 5; ++s) {
    const StepReport r = model.step(dt, {});
    EXPECT_GT(r.contraction_estimate, 1e5);
    const double lo1 = *std::min_element(p.temperature.begin(), p.temperature.end());
    const double hi1 = *std::max_element(p.temperature.begin(), p.temperature.end());
    EXPECT_GE(lo1, lo - slack) << "step " << s;
    EXPECT_LE(hi1, hi + slack) << "step " << s;
    lo = lo1, hi = hi1;
  }
  EXPECT_GE(lo, lo0 - slack);
  EXPECT_LE(hi, hi0 + slack);
  EXPECT_LT(hi - lo, hi0 - lo0);  // heat did flow
  EXPECT_NEAR(model.ledger().imbalance(), 0.0, 1e-9 * heat);
}

INSTANTIATE_TEST_SUITE_P(Solvers, StiffImplicit, ::testing::Values("cg", "direct", "auto"));

TEST(ThermalStiff, AutoPicksTheFactorisationWhenStiff) {
  Particles p = stiff_packing();
  const double dt = 1e6 * explicit_limit(p);
  ThermalModel model(p, {conductive()}, {});
  model.set_contacts(find_contacts(p));
  EXPECT_EQ(model.step(dt, {}).solver, "direct");
}

TEST(ThermalStiff, ExplicitBeyondLimitRefusedWithClearMessage) {
  Particles p = stiff_packing();
  const double dt = 1e6 * explicit_limit(p);
  const std::vector<double> before = p.temperature;
  ThermalSpec spec;
  spec.phi = 0;
  ThermalModel model(p, {conductive()}, spec);
  model.set_contacts(find_contacts(p));
  try {
    model.step(dt, {});
    FAIL() << "explicit step 1e6 x beyond its limit was accepted";
  } catch (const InputError& e) {
    const std::string msg = e.what();
    EXPECT_NE(msg.find("thermal.phi = 0"), std::string::npos) << msg;
    EXPECT_NE(msg.find("explicit stability limit"), std::string::npos) << msg;
    EXPECT_NE(msg.find("thermal.max_substeps"), std::string::npos) << msg;
  }
  EXPECT_EQ(p.temperature, before);  // nothing was half-done
}

TEST(ThermalStiff, ExplicitModeratelyBeyondLimitIsSubSteppedAndStable) {
  Particles p = stiff_packing();
  const double limit = explicit_limit(p);
  ThermalSpec spec;
  spec.phi = 0;
  ThermalModel model(p, {conductive()}, spec);
  model.set_contacts(find_contacts(p));
  const double lo0 = *std::min_element(p.temperature.begin(), p.temperature.end());
  const double hi0 = *std::max_element(p.temperature.begin(), p.temperature.end());
  for (int s = 0; s < 10; ++s) {
    const StepReport r = model.step(50.5 * limit, {});
    EXPECT_EQ(r.substeps, 51);
    EXPECT_EQ(r.solver, "explicit");
  }
  EXPECT_GE(*std::min_element(p.temperature.begin(), p.temperature.end()), lo0 - 1e-9);
  EXPECT_LE(*std::max_element(p.temperature.begin(), p.temperature.end()), hi0 + 1e-9);
  EXPECT_NEAR(model.ledger().stored, 0.0, 1e-12);
}

// Crank-Nicolson is stable at any step but monotone only below the same limit (its stiff modes
// are multiplied by ~-1 per step): beyond it the step is split, so no particle leaves the range
// of the starting temperatures; far beyond it the step is refused by name.
TEST(ThermalStiff, CrankNicolsonIsSubSteppedToKeepTheMaximumPrinciple) {
  for (const char* solver : {"cg", "direct"}) {
    Particles p = stiff_packing();
    ThermalSpec spec;
    spec.phi = 0.5;
    spec.solver = solver;
    spec.tolerance = 1e-12;
    ThermalModel model(p, {conductive()}, spec);
    model.set_contacts(find_contacts(p));
    const double limit = model.monotone_step_limit();
    ASSERT_NEAR(limit, 2.0 * explicit_limit(p), 1e-12 * limit);  // (1 - phi) halves the weight
    const double lo0 = *std::min_element(p.temperature.begin(), p.temperature.end());
    const double hi0 = *std::max_element(p.temperature.begin(), p.temperature.end());
    for (int s = 0; s < 5; ++s) EXPECT_EQ(model.step(50.5 * limit, {}).substeps, 51) << solver;
    EXPECT_GE(*std::min_element(p.temperature.begin(), p.temperature.end()), lo0 - 1e-9) << solver;
    EXPECT_LE(*std::max_element(p.temperature.begin(), p.temperature.end()), hi0 + 1e-9) << solver;
    try {
      model.step(1e6 * limit, {});
      FAIL() << "a Crank-Nicolson step 1e6 x beyond its monotone limit was accepted";
    } catch (const InputError& e) {
      const std::string msg = e.what();
      EXPECT_NE(msg.find("thermal.phi = 0.5"), std::string::npos) << msg;
      EXPECT_NE(msg.find("limit for a monotone step"), std::string::npos) << msg;
      EXPECT_NE(msg.find("use thermal.phi = 1"), std::string::npos) << msg;
    }
  }
}

// The limit holds whichever phase a sub-step reaches: with C_L < C_S it is taken with C_L even
// while every particle is still solid (one that melts in an early sub-step would otherwise make
// the later ones too long).
TEST(ThermalStiff, MonotoneLimitUsesTheSmallerHeatCapacity) {
  Particles p = test::chain(2, 1e-4);
  Material m = conductive();
  m.c_solid = 2000;
  m.c_liquid = 500;
  ThermalSpec spec;
  spec.phi = 0.5;
  ThermalModel model(p, {m}, spec);
  const auto contacts = find_contacts(p);
  model.set_contacts(contacts);
  const double g = contact_conductances(p, {m}, contacts)[0];
  const double c_liquid = test::solid_capacity(m, 0.6e-4, spec.time_scaling) * 500.0 / 2000.0;
  EXPECT_NEAR(model.monotone_step_limit(), c_liquid / (0.5 * g), 1e-12 * c_liquid / g);
}

// The case that showed it: five spheres in a row, the first at 1034 K, cooled in one long step.
TEST(ThermalStiff, CrankNicolsonLongStepOnAChainStaysAboveTheColdestParticle) {
  Particles p = test::chain(5, 1e-4);
  p.temperature[0] = 1034.0;
  Material m = conductive();
  ThermalSpec spec;
  spec.phi = 0.5;
  spec.solver = "direct";
  spec.max_substeps = 100000;
  ThermalModel model(p, {m}, spec);
  model.set_contacts(find_contacts(p));
  // 1000 x the limit, which is twice the explicit one (found with phi = 0: no circular check).
  ThermalSpec explicit_spec;
  explicit_spec.phi = 0;
  Particles copy = p;
  ThermalModel explicit_model(copy, {m}, explicit_spec);
  explicit_model.set_contacts(find_contacts(copy));
  const StepReport r = model.step(2e3 * explicit_model.monotone_step_limit(), {});
  EXPECT_EQ(r.substeps, 1000);
  for (double t : p.temperature) {
    EXPECT_GE(t, 300.0 - 1e-9);
    EXPECT_LE(t, 1034.0 + 1e-9);
  }
}

// A wall of 1e12 W/K holds the particle that touches it at theta_w: the heat the chain absorbs
// flows into the wall, by changes far below the last digit of 300 K. They must still reach the
// ledger: before, the solve's right side was dominated by g theta_w, CG stopped at once and the
// absorbed heat was in no bin (heat imbalance 1.0 in a lit run).
TEST(ThermalStiff, AWallOfHugeConductanceTakesTheHeatIntoTheLedger) {
  for (const char* solver : {"cg", "direct", "auto"}) {
    Particles p = test::chain(3, 1e-4);  // the first sphere touches x = 0
    ThermalSpec spec;
    spec.solver = solver;
    spec.walls.push_back({0, 0.0, 0.0, 300.0, 1e12});
    ThermalModel model(p, {conductive()}, spec);
    model.set_contacts(find_contacts(p));
    const std::vector<double> dh = {1e-12, 1e-12, 1e-12};
    for (int s = 0; s < 10; ++s) model.step(1e-9, dh);
    const ThermalLedger& l = model.ledger();
    EXPECT_DOUBLE_EQ(l.absorbed, 3e-11) << solver;
    EXPECT_NEAR(l.imbalance(), 0.0, 1e-9 * l.absorbed) << solver;
    EXPECT_GT(l.walls, 0.1 * l.absorbed) << solver;  // the chain conducts part of it out
    EXPECT_GT(l.stored, 0.0) << solver;
    for (double t : p.temperature) EXPECT_GE(t, 300.0) << solver;
  }
}

TEST(ThermalStiff, FixedPointBeyondItsLimitReportsFailure) {
  Particles p = stiff_packing();
  const double dt = 1e6 * explicit_limit(p);
  const std::vector<double> before = p.temperature;
  ThermalSpec spec;
  spec.solver = "fixed-point";
  ThermalModel model(p, {conductive()}, spec);
  model.set_contacts(find_contacts(p));
  try {
    model.step(dt, {});
    FAIL() << "fixed-point iteration returned from a step 1e6 x beyond its contraction limit";
  } catch (const RunError& e) {
    const std::string msg = e.what();
    EXPECT_NE(msg.find("fixed-point"), std::string::npos) << msg;
    EXPECT_NE(msg.find("diverge"), std::string::npos) << msg;
  }
  EXPECT_EQ(p.temperature, before);  // no unconverged field was written back
}

TEST(ThermalStiff, FixedPointJustBeyondConvergenceStagnatesOrDivergesLoudly) {
  // Near its limit the iteration crawls: within the cap it must either converge to the answer
  // of the direct solver or throw, never stop early with a wrong field.
  Particles p = stiff_packing();
  Particles q = p;
  const double dt = 2.0 * explicit_limit(p);
  ThermalSpec fp;
  fp.solver = "fixed-point";
  fp.max_iterations = 200;
  ThermalSpec direct;
  direct.solver = "direct";
  ThermalModel a(p, {conductive()}, fp), b(q, {conductive()}, direct);
  a.set_contacts(find_contacts(p));
  b.set_contacts(find_contacts(q));
  b.step(dt, {});
  try {
    a.step(dt, {});
    for (std::size_t i = 0; i < p.size(); ++i) EXPECT_NEAR(p.temperature[i], q.temperature[i], 1e-6);
  } catch (const RunError& e) {
    EXPECT_NE(std::string(e.what()).find("fixed-point"), std::string::npos);
  }
}

}  // namespace
}  // namespace beampack
