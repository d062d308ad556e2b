// Stiff steps: dt = 1e6 x the explicit limit. Backward Euler keeps the discrete maximum
// principle; explicit steps beyond the limit are sub-stepped or refused; the fixed-point iteration
// fails loudly.
#include <gtest/gtest.h>

#include <Eigen/Dense>
#include <Eigen/IterativeLinearSolvers>

#include <algorithm>
#include <functional>
#include <numbers>
#include <random>
#include <sstream>

#include <tbb/task_arena.h>

#include "geometry/contact.h"
#include "geometry/error.h"
#include "geometry/packing.h"
#include "tests/expect_error.h"
#include "tests/thermal_test_util.h"
#include "thermal/solvers.h"
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

// Steps of (3.10) on the conduction system assembled by hand, solved densely:
// (C + dt phi L) theta1 = (C - dt (1 - phi) L) theta0 + dH, with dH = heat (none when empty).
Eigen::VectorXd theta_method_by_hand(const Particles& p, const ThermalModel& model, double phi,
                                     double dt, int steps, const std::vector<double>& heat = {}) {
  const auto n = static_cast<Eigen::Index>(p.size());
  Eigen::VectorXd c(n), theta(n), dh = Eigen::VectorXd::Zero(n);
  for (Eigen::Index i = 0; i < n; ++i) {
    c[i] = model.thermal_mass(static_cast<std::size_t>(i));
    theta[i] = p.temperature[static_cast<std::size_t>(i)];
    if (!heat.empty()) dh[i] = heat[static_cast<std::size_t>(i)];
  }
  // K_ij A / d (3.2), K = 100 both.
  const Eigen::MatrixXd l = test::dense_conduction(
      n, find_contacts(p), [](const Contact& ct) { return 100.0 * ct.area / ct.distance; });
  const Eigen::MatrixXd implicit = Eigen::MatrixXd(c.asDiagonal()) + dt * phi * l;
  const Eigen::MatrixXd explicit_part = Eigen::MatrixXd(c.asDiagonal()) - dt * (1.0 - phi) * l;
  const Eigen::LDLT<Eigen::MatrixXd> solve(implicit);
  for (int s = 0; s < steps; ++s) theta = solve.solve(explicit_part * theta + dh);
  return theta;
}

Eigen::VectorXd start_temperatures() {
  const Particles p = stiff_packing();
  return Eigen::Map<const Eigen::VectorXd>(p.temperature.data(),
                                           static_cast<Eigen::Index>(p.size()));
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
  EXPECT_NEAR(model.ledger().imbalance(), 0.0, 1e-9 * heat);
  // The same five steps solved densely from (3.2) and the masses: (C + dt L) theta1 = C theta0.
  const Eigen::VectorXd exact = theta_method_by_hand(stiff_packing(), model, 1.0, dt, 5);
  const Eigen::VectorXd start = start_temperatures();
  EXPECT_GT((exact - start).cwiseAbs().maxCoeff(), 50.0);  // heat did flow, far
  for (std::size_t i = 0; i < p.size(); ++i)
    EXPECT_NEAR(p.temperature[i], exact[static_cast<Eigen::Index>(i)], 1e-6) << "particle " << i;
}

INSTANTIATE_TEST_SUITE_P(Solvers, StiffImplicit, ::testing::Values("cg", "direct", "auto"));

TEST(ThermalStiff, AutoPicksTheFactorisationWhenStiff) {
  Particles p = stiff_packing();
  const double dt = 1e6 * explicit_limit(p);
  ThermalModel model(p, {conductive()}, {});
  model.set_contacts(find_contacts(p));
  EXPECT_EQ(model.step(dt, {}).solver, "direct");
}

// "auto"'s bounds: 0.1 for the fixed-point iteration; 100 for CG up to 65536 rows; past them
// 100 (rows / 65536)^2, at most (max_iterations / 8)^2 and never below 100.
TEST(ThermalSolvers, AutoPicksBySizeAndStiffness) {
  const double above = 1 + 1e-12;
  for (const Eigen::Index rows : {2, 1000, 65536}) {
    EXPECT_STREQ(auto_solver(0.1, rows, 1000), "fixed-point");
    EXPECT_STREQ(auto_solver(0.1 * above, rows, 1000), "cg");
    EXPECT_STREQ(auto_solver(100, rows, 1000), "cg");
    EXPECT_STREQ(auto_solver(100 * above, rows, 1000), "direct");
  }
  EXPECT_STREQ(auto_solver(400, 131072, 1000), "cg");  // twice the rows: four times the bound
  EXPECT_STREQ(auto_solver(400 * above, 131072, 1000), "direct");
  EXPECT_STREQ(auto_solver(15625, 1'000'000, 1000), "cg");  // (1000 / 8)^2, below 100 x 15.3^2
  EXPECT_STREQ(auto_solver(15625 * above, 1'000'000, 1000), "direct");
  EXPECT_STREQ(auto_solver(2e4, 1'000'000, 2000), "cg");  // 100 x 15.26^2 = 23283 below 62500
  EXPECT_STREQ(auto_solver(23284, 1'000'000, 2000), "direct");
  EXPECT_STREQ(auto_solver(100, 1'000'000, 10), "cg");  // a small iteration cap keeps 100
  EXPECT_STREQ(auto_solver(100 * above, 1'000'000, 10), "direct");
}

// A chain of 150,000 spheres, every one heated (so every row is solved), one step at a contraction
// estimate of 300 (its bound there: 100 (150000 / 65536)^2 = 524): "auto" takes CG (the
// factorisation of a large bed of touching spheres costs ten times CG's at 1e6 rows), where a
// chain of 1000 at the same step is factorised; CG's temperatures are the factorisation's to its
// tolerance.
TEST(ThermalStiff, AutoTakesConjugateGradientsOnALargeModeratelyStiffSystem) {
  const double a = 1e-5;
  const auto step = [&](int n, const std::string& solver, double dt) {
    Particles p = test::chain(n, a);
    ThermalSpec spec;
    spec.solver = solver;
    ThermalModel model(p, {conductive()}, spec);
    model.set_contacts(find_contacts(p));
    std::vector<double> heat(p.size(), 0.0);
    for (std::size_t i = 0; i < p.size(); ++i) heat[i] = 1e-12 * static_cast<double>(i % 7);
    const StepReport report = model.step(dt, heat);
    return std::make_pair(report, p.temperature);
  };
  const double probe = 1e-12;
  const double dt = probe * 300.0 / step(4, "direct", probe).first.contraction_estimate;
  const auto [big, big_theta] = step(150'000, "auto", dt);
  EXPECT_NEAR(big.contraction_estimate, 300.0, 1e-6);
  EXPECT_EQ(big.solver, "cg") << big.solved_rows << " rows, " << big.iterations << " iterations";
  EXPECT_EQ(step(1000, "auto", dt).first.solver, "direct");
  const auto direct_theta = step(150'000, "direct", dt).second;
  double rise = 0;
  for (std::size_t i = 0; i < direct_theta.size(); ++i)
    rise = std::max(rise, direct_theta[i] - 300);
  ASSERT_GT(rise, 1.0);
  for (std::size_t i = 0; i < direct_theta.size(); ++i)
    ASSERT_NEAR(big_theta[i], direct_theta[i], 1e-7 * rise) << "particle " << i;
}

TEST(ThermalStiff, ExplicitBeyondLimitRefusedWithClearMessage) {
  Particles p = stiff_packing();
  const double dt = 1e6 * explicit_limit(p);
  const std::vector<double> before = p.temperature;
  ThermalSpec spec;
  spec.phi = 0;
  ThermalModel model(p, {conductive()}, spec);
  model.set_contacts(find_contacts(p));
  testing::expect_error<InputError>([&] { model.step(dt, {}); }, "thermal.phi = 0",
                                    "explicit stability limit", "thermal.max_substeps");
  EXPECT_EQ(p.temperature, before);  // nothing was half-done
}

// thermal.max_substeps is the most sub-steps a step may take: a step needing exactly that many
// runs, one needing one more is refused.
TEST(ThermalStiff, AStepNeedingExactlyTheMostSubStepsRuns) {
  for (const int most : {51, 50}) {
    Particles p = stiff_packing();
    const double limit = explicit_limit(p);
    ThermalSpec spec;
    spec.phi = 0;
    spec.max_substeps = most;
    ThermalModel model(p, {conductive()}, spec);
    model.set_contacts(find_contacts(p));
    if (most == 51) {
      EXPECT_EQ(model.step(50.5 * limit, {}).substeps, 51);
      continue;
    }
    testing::expect_error<InputError>([&] { model.step(50.5 * limit, {}); },
                                      "would need 51 sub-steps > thermal.max_substeps = 50");
  }
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
    // Every sub-step solves every row, and the counts say so (the run's "rows solved" share).
    EXPECT_EQ(r.live_rows, 51 * p.size());
    EXPECT_EQ(r.solved_rows, r.live_rows);
  }
  EXPECT_GE(*std::min_element(p.temperature.begin(), p.temperature.end()), lo0 - 1e-9);
  EXPECT_LE(*std::max_element(p.temperature.begin(), p.temperature.end()), hi0 + 1e-9);
  // Conduction moves heat, it makes none: what is stored is nothing, to round-off of the heat
  // content (an absolute 1e-12 J allowed ~1 K of one particle's heat).
  double heat = 0;
  for (std::size_t i = 0; i < p.size(); ++i) heat += model.thermal_mass(i) * p.temperature[i];
  EXPECT_NEAR(model.ledger().stored, 0.0, 1e-12 * heat);
  // And moves it as the explicit step says: the same 510 sub-steps of 50.5 / 51 limits, theta +=
  // -dt L theta / c with L from (3.2) by hand, agree to round-off (1.7e-11 K measured; bounds and
  // a zero ledger hold for any conservative, monotone update, e.g. one with half the conductance).
  const Eigen::VectorXd exact =
      theta_method_by_hand(stiff_packing(), model, 0.0, 50.5 * limit / 51, 10 * 51);
  EXPECT_GT((exact - start_temperatures()).cwiseAbs().maxCoeff(), 50.0);  // heat did flow, far
  for (std::size_t i = 0; i < p.size(); ++i)
    EXPECT_NEAR(p.temperature[i], exact[static_cast<Eigen::Index>(i)], 1e-9) << "particle " << i;
}

// A step beyond the limit is split into n sub-steps of dt / n, each with 1/n of the step's heat:
// it equals n steps of dt / n taken one by one, to the bit, for explicit Euler and for
// Crank-Nicolson. (Nothing else checked a split step's length: sub-steps of dt / (2 n), half the
// conduction time, passed every test.)
TEST(ThermalStiff, ASplitStepEqualsItsSubStepsTakenOneByOne) {
  for (double phi : {0.0, 0.5}) {
    Particles whole = stiff_packing(), parts = stiff_packing();
    ThermalSpec spec;
    spec.phi = phi;
    spec.skip_resting = false;  // the same rows solved both ways
    ThermalModel a(whole, {conductive()}, spec), b(parts, {conductive()}, spec);
    const auto contacts = find_contacts(whole);
    a.set_contacts(contacts), b.set_contacts(contacts);
    std::vector<double> heat(whole.size(), 0.0);
    for (std::size_t i = 0; i < heat.size(); i += 37) heat[i] = 100.0 * a.thermal_mass(i);
    const double dt = 20.5 * a.monotone_step_limit();
    const StepReport r = a.step(dt, heat);
    ASSERT_EQ(r.substeps, 21) << "phi " << phi;
    std::vector<double> share(heat.size());
    for (std::size_t i = 0; i < heat.size(); ++i) share[i] = heat[i] / r.substeps;
    for (int k = 0; k < r.substeps; ++k) ASSERT_EQ(b.step(dt / r.substeps, share).substeps, 1);
    EXPECT_EQ(whole.temperature, parts.temperature) << "phi " << phi;
    EXPECT_EQ(a.ledger().stored, b.ledger().stored) << "phi " << phi;
    EXPECT_GT(std::abs(whole.temperature[0] - stiff_packing().temperature[0]), 1.0);  // it moved
    // Both ways are the step (3.10) itself, not only each other: the sub-steps by hand agree, and
    // particles no deposit touched moved by conduction alone (particle 0's move above is mostly
    // its own heating). The solves of phi = 0.5 stop at thermal.tolerance = 1e-10 of a change of
    // ~100 K a sub-step (2.8e-9 K measured; explicit: 1e-12 K).
    const Eigen::VectorXd exact =
        theta_method_by_hand(stiff_packing(), a, phi, dt / r.substeps, r.substeps, share);
    const Eigen::VectorXd start = start_temperatures();
    double unheated_move = 0;
    for (std::size_t i = 0; i < heat.size(); ++i) {
      const auto k = static_cast<Eigen::Index>(i);
      if (heat[i] == 0) unheated_move = std::max(unheated_move, std::abs(exact[k] - start[k]));
      EXPECT_NEAR(whole.temperature[i], exact[k], phi == 0 ? 1e-9 : 1e-6)
          << "phi " << phi << ", particle " << i;
    }
    EXPECT_GT(unheated_move, 10.0) << "phi " << phi;
  }
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
    testing::expect_error<InputError>([&] { model.step(1e6 * limit, {}); }, "thermal.phi = 0.5",
                                      "limit for a monotone step", "use thermal.phi = 1");
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

// A chain joined by K = 1e9 at dt = 1e-3 s (dt G / c ~ 1e13): every solver must keep the
// cluster's energy, c^T theta1 = c^T theta0 + dH, to round-off. CG stops at a residual relative
// to its drive dt Q(theta0) + dH, which here is ~1e13 times the change: before each cluster's
// energy was restored, CG ended with the chain at 365 K where the energy says 552.8 K, and the
// ledger open by 1.7 times the heat absorbed.
TEST(ThermalStiff, EverySolverKeepsAStiffClustersEnergy) {
  Material m = conductive();
  m.conductivity = 1e9;
  std::vector<double> reference;
  for (const char* solver : {"direct", "cg", "auto"}) {
    Particles p = test::chain(4, 1e-4);
    p.temperature[0] = 690.0;
    ThermalSpec spec;
    spec.solver = solver;
    ThermalModel model(p, {m}, spec);
    model.set_contacts(find_contacts(p));
    double energy = 1e-9, mass = 0;  // c^T theta after the step, and c^T 1
    for (std::size_t i = 0; i < p.size(); ++i) {
      energy += model.thermal_mass(i) * p.temperature[i];
      mass += model.thermal_mass(i);
    }
    const std::vector<double> dh = {0.0, 0.0, 0.0, 1e-9};
    model.step(1e-3, dh);
    const ThermalLedger& l = model.ledger();
    EXPECT_NEAR(l.imbalance(), 0.0, 1e-12 * l.absorbed) << solver;
    // One temperature throughout (the conductance is 1e13 times the capacity per step).
    for (double t : p.temperature) EXPECT_NEAR(t, energy / mass, 1e-6) << solver;
    if (reference.empty()) reference = p.temperature;
    for (std::size_t i = 0; i < p.size(); ++i)
      EXPECT_NEAR(p.temperature[i], reference[i], 1e-6) << solver;
  }
}

// A chain at 300 K without walls, warmed by 1e-3 K a step through stiff steps (dt G / c ~ 1e3 to
// 1e5), factorised: the solve measures temperatures from the coolest particle's, so the
// factorisation's round-off is ~1e-16 of the rise, not of 300 K. Measured from 0 K it opened the
// ledger by 2.5e-11 to 6.3e-11 of the heat here (the DEM bed at the paper's step: 3.6e-5, and a
// warning); now what is left, 6e-13 to 1.4e-12, is the rounding of the rises into the
// temperatures themselves, which the ledger books as the particles keep them.
TEST(ThermalStiff, AFaintlyWarmedStiffChainWithoutWallsKeepsItsLedger) {
  for (const double k : {1e4, 1e6}) {
    Material m = conductive();
    m.conductivity = k;
    Particles p = test::chain(20, 1e-4);
    ThermalSpec spec;
    spec.solver = "direct";
    ThermalModel model(p, {m}, spec);
    model.set_contacts(find_contacts(p));
    std::vector<double> dh(p.size(), 0.0);
    dh[0] = 1e-3 * 20 * model.thermal_mass(0);  // the chain's mean rises 1e-3 K a step
    for (int step = 0; step < 10; ++step) model.step(1e-3, dh);
    const ThermalLedger& l = model.ledger();
    EXPECT_NEAR(l.imbalance(), 0.0, 5e-12 * l.absorbed) << "K " << k;
    EXPECT_NEAR(p.temperature[19], 300.01, 1e-4) << "K " << k;
  }
}

// A rise below the last digit of a temperature is lost to the particle, and the ledger books
// what the particle keeps: nothing stored, open by all the heat. (It booked the solve's change,
// relative to the starting temperature, and closed while the heat was nowhere; review finding.)
TEST(ThermalStiff, ARiseATemperatureCannotHoldOpensTheLedger) {
  for (const char* solver : {"direct", "cg"}) {
    Particles q = test::chain(2, 1e-4);  // two in contact: the solver runs
    ThermalSpec spec;
    spec.solver = solver;
    ThermalModel model(q, {conductive()}, spec);
    model.set_contacts(find_contacts(q));
    const std::vector<double> dh = {1e-15 * model.thermal_mass(0), 0.0};  // a rise of 1e-15 K
    EXPECT_TRUE(model.step(1e-9, dh).conduction_ran) << solver;
    EXPECT_EQ(q.temperature, std::vector<double>(2, 300.0)) << solver;
    EXPECT_EQ(model.ledger().stored, 0.0) << solver;
    EXPECT_EQ(model.ledger().imbalance(), model.ledger().absorbed) << solver;
  }
}

// A stiff chain that touches a wall of almost no conductance is as nearly singular as an
// insulated one: the factorisation must keep its energy too (it lost 1e-5 of the absorbed heat
// at g = 1e-20 W/K, grounded only insulated clusters). With the wall's share: c^T (theta1 -
// theta0) = dH - walls.
TEST(ThermalStiff, AStiffClusterTouchingAWeakWallKeepsItsEnergy) {
  Material m = conductive();
  m.conductivity = 1e9;
  for (const double g : {1e-20, 1e-12, 1e-6}) {
    for (const char* solver : {"direct", "cg", "auto"}) {
      Particles p = test::chain(3, 1e-4);  // the first sphere touches x = 0
      ThermalSpec spec;
      spec.solver = solver;
      spec.walls.push_back({0, 0.0, 1e-5, 200.0, g});
      ThermalModel model(p, {m}, spec);
      model.set_contacts(find_contacts(p));
      const std::vector<double> dh = {0.0, 0.0, 1e-9};
      for (int s = 0; s < 3; ++s) model.step(1e-3, dh);
      const ThermalLedger& l = model.ledger();
      EXPECT_NEAR(l.imbalance(), 0.0, 1e-12 * l.absorbed) << solver << " g = " << g;
      EXPECT_NE(l.walls, 0.0) << solver << " g = " << g;  // the wall takes its (tiny) share
    }
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
  testing::expect_error<RunError>([&] { model.step(dt, {}); }, "fixed-point", "diverge");
  EXPECT_EQ(p.temperature, before);  // no unconverged field was written back
}

// Twice the explicit limit: the contraction estimate dt phi max_i (2 sum_j G_ij + W_i) / c_i is 4
// here (the iteration matrix's spectral radius, which it bounds, is above 1 too), so the update
// grows from its first iterations: the divergence check must fire, naming the failure, within the
// cap (a SolverRefusal: a refusal with advice, which validate --stiff counts as refused, not
// failed), and no unconverged field may be written back.
TEST(ThermalStiff, FixedPointJustBeyondConvergenceDivergesLoudly) {
  Particles p = stiff_packing();
  const double dt = 2.0 * explicit_limit(p);
  const std::vector<double> before = p.temperature;
  ThermalSpec fp;
  fp.solver = "fixed-point";
  fp.max_iterations = 200;
  ThermalModel a(p, {conductive()}, fp);
  a.set_contacts(find_contacts(p));
  testing::expect_error<SolverRefusal>([&] { a.step(dt, {}); },
                                       "fixed-point iteration (3.11) diverges");
  EXPECT_EQ(p.temperature, before);
}

// CG stopped by its iteration cap declines the step with advice, as the fixed-point iteration
// does past its limit: a SolverRefusal, which the stability grid counts as refused; any other
// RunError (a NaN) is a failure there.
TEST(ThermalStiff, CgAtItsIterationCapRefusesTheStep) {
  Particles p = stiff_packing();
  ThermalSpec spec;
  spec.solver = "cg";
  spec.max_iterations = 2;
  ThermalModel model(p, {conductive()}, spec);
  model.set_contacts(find_contacts(p));
  testing::expect_error<SolverRefusal>([&] { model.step(1e6 * explicit_limit(p), {}); },
                                       "did not reach thermal.tolerance");
}

// A corrector pass starts from the last pass's change. With a heat capacity 1e17 times below the
// latent band's (c_solid = 1e-14 J/(kg K), inside the run file's range), the predictor's change
// is ~1e17 K: the fixed-point iteration's first update cancelled it to exactly 0 and the step was
// refused as divergent (also under "auto", which had picked fixed-point for the corrector). A
// guess worse than none is dropped, and "auto" factorises when an iterative solve fails.
TEST(ThermalStiff, ACorrectorFarFromThePredictorStillSolvesEverySolver) {
  const double r = 1e-4;
  Material m;
  m.c_solid = 1e-14;
  m.conductivity = 100;
  const double g = 100.0 * std::numbers::pi * (r * r - 0.5625 * r * r) / (1.5 * r);
  const double mass = 1000.0 * 4.0 / 3.0 * std::numbers::pi * r * r * r / 1e6;  // m / M
  const double c_predictor = mass * m.c_solid, c_band = mass * (m.c_solid + m.latent_melt);
  auto step = [&](const std::string& solver, double dt) {
    Particles p;
    p.add(Vec3::Zero(), r, 0, 590.0);
    p.add(Vec3(1.5 * r, 0, 0), r, 0, 590.0);
    ThermalSpec spec;
    spec.solver = solver;
    ThermalModel model(p, {m}, spec);
    model.set_contacts(find_contacts(p));
    const StepReport report = model.step(dt, {c_band * 20.0, 0.0});
    EXPECT_TRUE(report.phase_corrected) << solver;
    EXPECT_NEAR(model.ledger().imbalance(), 0.0, 1e-9 * model.ledger().absorbed) << solver;
    return p.temperature;
  };
  // Fixed-point throughout (each pass contracts: dt 2 G / c = 0.01 for the predictor).
  const double gentle = 0.01 * c_predictor / (2.0 * g);
  const auto direct = step("direct", gentle);
  const auto fixed_point = step("fixed-point", gentle);
  for (int i = 0; i < 2; ++i) EXPECT_NEAR(fixed_point[i], direct[i], 1e-6) << i;
  EXPECT_GT(direct[0], 599.0);  // heated up to the melt band (the corrector applied it)
  // Stiff for the predictor (auto factorises), gentle for the corrector (auto: fixed-point).
  const double stiff = 1e3 * c_predictor / (2.0 * g);
  const auto reference = step("direct", stiff);
  const auto automatic = step("auto", stiff);
  for (int i = 0; i < 2; ++i) EXPECT_NEAR(automatic[i], reference[i], 1e-6) << i;
}

// "auto" promises an answer: when the fixed-point iteration it picked fails (here: a cap of 3
// iterations where a contraction of 0.05 needs ~8), the step is factorised instead; asked for by
// name, the fixed-point iteration's failure is the step's.
TEST(ThermalStiff, AutoFactorisesWhenItsFixedPointIterationFails) {
  const double r = 1e-4;
  const Material m = conductive();
  const double g = 100.0 * std::numbers::pi * (r * r - 0.5625 * r * r) / (1.5 * r);
  const double c = 1000.0 * 4.0 / 3.0 * std::numbers::pi * r * r * r * 1000.0 / 1e6;  // m C_S / M
  auto step = [&](const std::string& solver) {
    Particles p;
    p.add(Vec3::Zero(), r, 0, 500.0);
    p.add(Vec3(1.5 * r, 0, 0), r, 0, 300.0);
    ThermalSpec spec;
    spec.solver = solver;
    spec.max_iterations = 3;
    ThermalModel model(p, {m}, spec);
    model.set_contacts(find_contacts(p));
    const StepReport report = model.step(0.05 * c / (2.0 * g), {});
    EXPECT_EQ(report.solver, solver == "auto" ? "direct" : solver);
    return p.temperature;
  };
  EXPECT_THROW(step("fixed-point"), SolverRefusal);
  const auto automatic = step("auto"), direct = step("direct");
  for (int i = 0; i < 2; ++i) EXPECT_EQ(automatic[i], direct[i]) << i;
}

// Stagnation (solvers.cpp): just below the limit the iteration converges, but too slowly for the
// cap. Two equal spheres, backward Euler: the iteration (3.11) theta <- theta + (b - A theta) / c
// has the matrix -dt G / c [[1, -1], [-1, 1]], eigenvalues 0 and -2 dt G / c. With 2 dt G / c =
// 0.999 the difference mode shrinks by 0.999 an iteration: from a relative update ~0.1 to the
// tolerance 1e-10 takes ln(1e-9) / ln(0.999) ~ 2e4 iterations, far beyond a cap of 200, while the
// update never grows (no divergence). The window check (20 iterations) must say it stagnates, at
// iteration 21, long before the cap, and write nothing back.
TEST(ThermalStiff, FixedPointCrawlingJustBelowItsLimitReportsStagnation) {
  const double r = 1e-4;
  Particles p;
  p.add(Vec3::Zero(), r, 0, 500.0);
  p.add(Vec3(1.5 * r, 0, 0), r, 0, 300.0);
  const Material m = conductive();
  // G = K A / d (3.2) with L_i = d / 2 for equal radii (3.9): A = pi (r^2 - (0.75 r)^2).
  const double g = 100.0 * std::numbers::pi * (r * r - 0.5625 * r * r) / (1.5 * r);
  const double c = 1000.0 * 4.0 / 3.0 * std::numbers::pi * r * r * r * 1000.0 / 1e6;  // m C_S / M
  const double dt = 0.999 * c / (2.0 * g);
  ThermalSpec spec;
  spec.solver = "fixed-point";
  spec.max_iterations = 200;
  ThermalModel model(p, {m}, spec);
  const auto contacts = find_contacts(p);
  ASSERT_EQ(contacts.size(), 1u);
  ASSERT_NEAR(contact_conductances(p, {m}, contacts)[0] / g, 1.0, 1e-12);
  model.set_contacts(contacts);
  testing::expect_error<SolverRefusal>([&] { model.step(dt, {}); },
                                       "fixed-point iteration (3.11) stagnates at iteration 21",
                                       "= 0.999;");  // the contraction estimate
  EXPECT_EQ(p.temperature[0], 500.0);
  EXPECT_EQ(p.temperature[1], 300.0);
  // The same step with a cap the crawl can meet converges to the exact backward-Euler answer:
  // the difference 200 K decays by 1 / (1 + 2 dt G / c) = 1 / 1.999, the mean stays 400 K.
  spec.max_iterations = 100000;
  ThermalModel patient(p, {m}, spec);
  patient.set_contacts(contacts);
  patient.step(dt, {});
  EXPECT_NEAR(p.temperature[0], 400.0 + 100.0 / 1.999, 1e-6);
  EXPECT_NEAR(p.temperature[1], 400.0 - 100.0 / 1.999, 1e-6);
  // At 0.99 of the limit the crawl needs ~2300 iterations: more than ten times the 179 left
  // after the window, so it is stagnation too, said as early (not "did not converge" at 200).
  spec.max_iterations = 200;
  ThermalModel slow(p, {m}, spec);
  slow.set_contacts(contacts);
  testing::expect_error<SolverRefusal>([&] { slow.step(0.99 * c / (2.0 * g), {}); },
                                       "fixed-point iteration (3.11) stagnates at iteration 21");
}

// Below its limit the iteration converges, and must say nothing else. Chains of spheres whose
// radii span 10^2.5, dt set so that the iteration matrix's spectral radius is 0.97 (from the
// eigenvalues of c^{-1/2} L c^{-1/2}): the largest update can grow for a few iterations (c is far
// from uniform), which the checks on it called divergence (seed 10: "diverges at iteration 4")
// or stagnation (seeds 24 and 64: "stagnates at iteration 21"), though ~800 iterations reach the
// tolerance. Every step must converge, within the cap, to the factorised answer to within what
// the tolerance leaves.
TEST(ThermalStiff, FixedPointThatConvergesIsNeitherDivergentNorStagnant) {
  Material m = conductive();
  for (int seed = 0; seed < 80; ++seed) {
    std::mt19937_64 rng(static_cast<std::uint64_t>(seed));
    std::uniform_real_distribution<double> u(0.0, 1.0);
    const int n = 6 + static_cast<int>(rng() % 20);
    Particles p;
    double x = 0;
    for (int i = 0; i < n; ++i) {
      const double r = 1e-5 * std::pow(10.0, 2.5 * u(rng));
      if (i > 0) x += 0.9 * (r + p.radius.back()) * (0.5 + 0.5 * u(rng));
      p.add(Vec3(x, 0, 0), r, 0, 300.0 + 100.0 * u(rng));
    }
    const auto contacts = find_contacts(p);
    const std::vector<double> g = contact_conductances(p, {m}, contacts);
    ThermalSpec spec;
    spec.solver = "fixed-point";
    spec.skip_resting = false;
    ThermalModel probe(p, {m}, spec);
    Eigen::VectorXd root_c(n);
    for (int i = 0; i < n; ++i) root_c[i] = std::sqrt(probe.thermal_mass(std::size_t(i)));
    const Eigen::MatrixXd l = test::dense_conduction(
        n, contacts, [&](const Contact& ct) { return g[std::size_t(&ct - contacts.data())]; });
    const Eigen::MatrixXd scaled =
        root_c.cwiseInverse().asDiagonal() * l * root_c.cwiseInverse().asDiagonal();
    const double dt =
        0.97 / Eigen::SelfAdjointEigenSolver<Eigen::MatrixXd>(scaled).eigenvalues().maxCoeff();
    std::vector<double> heat(std::size_t(n), 0.0);
    heat[rng() % std::size_t(n)] = 1e-12;
    Particles iterated = p, factorised = p;
    ThermalModel fixed_point(iterated, {m}, spec);
    spec.solver = "direct";
    ThermalModel direct(factorised, {m}, spec);
    fixed_point.set_contacts(contacts), direct.set_contacts(contacts);
    try {
      fixed_point.step(dt, heat);
    } catch (const RunError& e) {
      ADD_FAILURE() << "seed " << seed << ": " << e.what();
      continue;
    }
    direct.step(dt, heat);
    // Stopped at an update of tolerance x the largest change: the error left is at most
    // rho / (1 - rho) updates in the weighted norm, sqrt(c_max / c_min) times that in any one
    // particle.
    double change = 0;
    for (int i = 0; i < n; ++i)
      change = std::max(
          change, std::abs(factorised.temperature[std::size_t(i)] - p.temperature[std::size_t(i)]));
    const double bound =
        spec.tolerance * change * (0.97 / 0.03) * (root_c.maxCoeff() / root_c.minCoeff());
    for (int i = 0; i < n; ++i)
      EXPECT_NEAR(iterated.temperature[std::size_t(i)], factorised.temperature[std::size_t(i)],
                  bound)
          << "seed " << seed << ", particle " << i;
  }
}

}  // namespace
}  // namespace beampack

namespace beampack {
namespace {

// Two spheres joined by K = 1e20 over dt = 1e-6 s (dt G / c ~ 1e25): the step's matrix is singular
// to doubles. CG broke down into NaN after its 1000 iterations and the run failed as a defect
// (RunError); it is a refusal with advice, and "direct" and "auto" give the common temperature.
TEST(ThermalStiff, ConjugateGradientsRefuseAMatrixSingularToDoubles) {
  Material m = conductive();
  m.conductivity = 1e20;
  for (const char* solver : {"cg", "direct", "auto"}) {
    SCOPED_TRACE(solver);
    Particles p = test::chain(2, 2e-4);
    p.temperature[0] = 400.0;
    ThermalSpec spec;
    spec.solver = solver;
    spec.phi = 1.0;
    spec.time_scaling = 1e6;  // the presets' M: c = m C / M, 1e-6 of the particles' own
    ThermalModel model(p, {m}, spec);
    model.set_contacts(find_contacts(p));
    const double c = model.thermal_mass(0);  // both alike
    const auto five_steps = [&] {  // a deposit in the second: the first has none to break on
      for (int k = 0; k < 5; ++k)
        model.step(1e-6, k == 1 ? std::vector<double>{1e-12, 0.0} : std::vector<double>{});
    };
    if (std::string(solver) != "cg") {
      five_steps();
      const double mean = 350.0 + 1e-12 / (2 * c);
      EXPECT_NEAR(p.temperature[0], mean, 1e-9);
      EXPECT_NEAR(p.temperature[1], mean, 1e-9);
      continue;
    }
    testing::expect_error<SolverRefusal>(five_steps, "use thermal.solver = \"direct\"");
  }
}

}  // namespace
}  // namespace beampack

namespace beampack {
namespace {

// The solvers' parallel product, row by row, against Eigen's a * x: the same bits with one thread
// and two (seeded, symmetric, 3e4 rows and ~1.5e5 entries: above the parallel threshold), and for
// a matrix not compressed. A row summed in another order differs in its last bits.
TEST(ThermalSolvers, TheParallelProductIsEigensBitForBitOnAnyThreadCount) {
  const Eigen::Index n = 30000;
  std::mt19937_64 rng(2013);
  std::uniform_real_distribution<double> u(-1.0, 1.0);
  std::uniform_int_distribution<Eigen::Index> pick(0, n - 1);
  std::vector<Eigen::Triplet<double>> entries;
  for (Eigen::Index i = 0; i < n; ++i) {
    entries.emplace_back(i, i, 10.0 + u(rng));
    for (int e = 0; e < 2; ++e) {
      const Eigen::Index j = pick(rng);
      const double v = u(rng);
      if (j != i) entries.emplace_back(i, j, v), entries.emplace_back(j, i, v);
    }
  }
  SparseMatrix a(n, n);
  a.setFromTriplets(entries.begin(), entries.end());
  ASSERT_GT(a.nonZeros(), 100000);
  Eigen::VectorXd x(n);
  for (double& v : x) v = 300.0 + u(rng);
  const Eigen::VectorXd eigen = a * x;
  SparseMatrix loose = a;
  loose.reserve(Eigen::VectorXi::Constant(n, 2));  // room after every column: not compressed
  ASSERT_FALSE(loose.isCompressed());
  for (const int threads : {1, 2}) {
    tbb::task_arena arena(threads);
    Eigen::VectorXd y, y_loose;
    arena.execute([&] { y = symmetric_product(a, x), y_loose = symmetric_product(loose, x); });
    for (Eigen::Index i = 0; i < n; ++i) {
      ASSERT_EQ(y[i], eigen[i]) << threads << " threads, row " << i;
      ASSERT_EQ(y_loose[i], eigen[i]) << threads << " threads, row " << i;
    }
  }
}

// A seeded SPD system of 3e4 rows with a step matrix's shape (a conductance graph's Laplacian
// plus a positive diagonal), its right-hand side, and a guess.
struct SeededSystem {
  SparseMatrix a;
  Eigen::VectorXd rhs, guess;
};
SeededSystem seeded_step_like_system() {
  const Eigen::Index n = 30000;
  std::mt19937_64 rng(7);
  std::uniform_real_distribution<double> u(0.0, 1.0);
  std::uniform_int_distribution<Eigen::Index> pick(0, n - 1);
  std::vector<Eigen::Triplet<double>> entries;
  Eigen::VectorXd diagonal = Eigen::VectorXd::Zero(n);
  for (Eigen::Index i = 0; i < n; ++i)
    for (int e = 0; e < 2; ++e) {
      const Eigen::Index j = pick(rng);
      const double g = u(rng);
      if (j == i) continue;
      entries.emplace_back(i, j, -g), entries.emplace_back(j, i, -g);
      diagonal[i] += g, diagonal[j] += g;
    }
  for (Eigen::Index i = 0; i < n; ++i) entries.emplace_back(i, i, diagonal[i] + 0.05 + u(rng));
  SparseMatrix a(n, n);
  a.setFromTriplets(entries.begin(), entries.end());
  Eigen::VectorXd rhs(n);
  for (double& v : rhs) v = u(rng) - 0.5;
  return {a, rhs, Eigen::VectorXd::Constant(n, 0.01)};
}

using EigenCg = Eigen::ConjugateGradient<SparseMatrix, Eigen::Lower | Eigen::Upper,
                                         Eigen::DiagonalPreconditioner<double>>;

// cg_solve against Eigen's ConjugateGradient with the diagonal preconditioner, which it follows
// step for step with its products and updates over threads: the same iterations, residual and
// bits with one thread and two.
TEST(ThermalSolvers, ConjugateGradientsAreEigensBitForBitOnAnyThreadCount) {
  const SeededSystem system = seeded_step_like_system();  // no structured binding: clang 14
  const SparseMatrix& a = system.a;                       // cannot capture one in a lambda
  const Eigen::VectorXd &rhs = system.rhs, &guess = system.guess;
  const Eigen::Index n = a.rows();
  for (const double tolerance : {1e-3, 1e-5, 1e-7, 1e-10}) {  // where each stops differs
    EigenCg eigen;
    eigen.setTolerance(tolerance);
    eigen.setMaxIterations(1000);
    eigen.compute(a);
    const Eigen::VectorXd expected = eigen.solveWithGuess(rhs, guess);
    ASSERT_EQ(eigen.info(), Eigen::Success);
    ASSERT_GT(eigen.iterations(), 2);
    for (const int threads : {1, 2}) {
      tbb::task_arena arena(threads);
      Eigen::VectorXd theta = guess;
      SolveStats stats;
      arena.execute([&] { stats = cg_solve(a, rhs, theta, tolerance, 1000); });
      const std::string at =
          std::to_string(threads) + " threads, tolerance " + std::to_string(tolerance);
      EXPECT_EQ(stats.iterations, eigen.iterations()) << at;
      EXPECT_EQ(stats.error, eigen.error()) << at;
      for (Eigen::Index i = 0; i < n; ++i) ASSERT_EQ(theta[i], expected[i]) << at << ", row " << i;
    }
  }
  // Its ends: a zero right-hand side (zero, at once), a guess already converged (kept, no
  // iteration), and the iteration cap (a refusal naming Eigen's residual at the cap).
  Eigen::VectorXd theta = guess;
  EXPECT_EQ(cg_solve(a, Eigen::VectorXd::Zero(n), theta, 1e-10, 1000).iterations, 0);
  EXPECT_TRUE(theta.isZero(0.0));
  Eigen::VectorXd converged = guess;
  cg_solve(a, rhs, converged, 1e-10, 1000);
  theta = converged;
  EXPECT_EQ(cg_solve(a, rhs, theta, 1e-10, 1000).iterations, 0);
  EXPECT_EQ(theta, converged);
  EigenCg capped;
  capped.setTolerance(1e-10);
  capped.setMaxIterations(3);
  capped.compute(a);
  const Eigen::VectorXd at_cap = capped.solveWithGuess(rhs, guess);  // evaluated: it is lazy
  ASSERT_NE(capped.info(), Eigen::Success);
  std::ostringstream residual;
  residual << "(relative residual " << capped.error() << ")";
  theta = guess;
  testing::expect_error<SolverRefusal>([&] { cg_solve(a, rhs, theta, 1e-10, 3); }, residual.str());
}

// cg_solve stops where its tolerance says, to the pass: with the tolerance just above the relative
// residual Eigen reaches after k passes, it stops after pass k (a threshold a tenth tighter goes
// on), and just below the residual after k - 1 passes, it still stops after pass k (one a tenth
// looser stops sooner). Four tolerances a few decades apart could not tell those apart. Eigen's
// count, which cg_solve keeps, is k - 1 then: a pass that converges is not counted, and a pass
// capped by the maximum is.
TEST(ThermalSolvers, ConjugateGradientsStopAtTheirToleranceToTheIteration) {
  const SeededSystem system = seeded_step_like_system();
  const SparseMatrix& a = system.a;
  const Eigen::VectorXd &rhs = system.rhs, &guess = system.guess;
  const auto residual_at = [&](int iterations) {
    EigenCg capped;
    capped.setTolerance(1e-300);
    capped.setMaxIterations(iterations);
    capped.compute(a);
    const Eigen::VectorXd x = capped.solveWithGuess(rhs, guess);  // evaluated: it is lazy
    EXPECT_EQ(capped.iterations(), iterations);
    return capped.error();
  };
  for (const int k : {2, 5, 12, 30}) {
    const double before = residual_at(k - 1), at = residual_at(k);
    ASSERT_LT(at, 0.8 * before) << "pass " << k << ": the residual must fall to tell them";
    for (const double tolerance : {at * (1 + 1e-9), before * (1 - 1e-9)}) {
      Eigen::VectorXd theta = guess;
      const SolveStats stats = cg_solve(a, rhs, theta, tolerance, 1000);
      EXPECT_EQ(stats.iterations, k - 1)
          << "tolerance " << tolerance << ", between the residuals " << before << " and " << at;
      EXPECT_LT(stats.error, tolerance);
    }
  }
}

// A non-finite result from non-finite inputs is a defect upstream, a RunError that is no
// SolverRefusal, so "auto" does not fall back to the factorisation on it and hide it; from finite
// inputs it is the solver's own breakdown, a refusal. The fixed-point iteration called both a
// refusal.
TEST(ThermalStiff, NonFiniteInputsAreADefectNotARefusal) {
  SparseMatrix a(2, 2);
  a.insert(0, 0) = 2.0, a.insert(1, 1) = 2.0, a.insert(0, 1) = -1.0, a.insert(1, 0) = -1.0;
  const Eigen::VectorXd c = Eigen::VectorXd::Constant(2, 2.0);
  const Eigen::VectorXd bad = Eigen::Vector2d(1.0, std::nan(""));
  const auto kind = [](const std::function<void()>& solve) {
    try {
      solve();
    } catch (const SolverRefusal&) {
      return "refusal";
    } catch (const RunError&) {
      return "defect";
    }
    return "none";
  };
  Eigen::VectorXd theta = Eigen::VectorXd::Zero(2);
  EXPECT_STREQ(kind([&] { fixed_point_solve(a, c, bad, theta, 1e-10, 100, 0.5); }), "defect");
  theta.setZero();
  EXPECT_STREQ(kind([&] { cg_solve(a, bad, theta, 1e-10, 100); }), "defect");
  // Finite inputs past the iteration's limit: a refusal (c far below the coupling diverges).
  theta.setZero();
  const Eigen::VectorXd small_c = Eigen::VectorXd::Constant(2, 0.1);
  EXPECT_STREQ(kind([&] {
                 fixed_point_solve(a, small_c, Eigen::Vector2d(1.0, 0.0), theta, 1e-10, 1000, 20);
               }),
               "refusal");
}

}  // namespace
}  // namespace beampack
