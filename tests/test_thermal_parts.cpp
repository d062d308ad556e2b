// Inputs, the conductance graph, what runs and what is skipped, solver agreement, the reuse of
// the direct factorisation, and save/restore for the stagger.
#include <gtest/gtest.h>
#include <tbb/task_arena.h>

#include <cmath>
#include <cstdlib>
#include <random>
#include <sstream>

#include "geometry/contact.h"
#include "geometry/error.h"
#include "geometry/packing.h"
#include "tests/expect_error.h"
#include "tests/long_tests.h"
#include "thermal/thermal_model.h"

namespace beampack {
namespace {

TEST(ThermalInput, MaterialMessagesNameKeyValueAndLimit) {
  Material m;
  m.conductivity = -3;
  EXPECT_EQ(testing::error_message<InputError>([&] { m.validate(); }),
            "material.conductivity = -3: must be >= 0");
  Material v;
  v.vapor_temperature = 500;
  EXPECT_EQ(testing::error_message<InputError>([&] { v.validate("material[1]"); }),
            "material[1].vapor_temperature = 500: must be > material[1].melt_temperature = 600");
  Material d;
  d.density = std::nan("");
  EXPECT_CONTAINS(testing::error_message<InputError>([&] { d.validate(); }),
                  "material.density = nan");
  // The boundaries: theta_v = theta_m is no liquid range (refused), each latent band is checked.
  Material equal;
  equal.vapor_temperature = equal.melt_temperature;
  EXPECT_EQ(testing::error_message<InputError>([&] { equal.validate(); }),
            "material.vapor_temperature = 600: must be > material.melt_temperature = 600");
  for (double Material::*band :
       {&Material::latent_melt, &Material::latent_solidify, &Material::latent_vapor})
    for (const double bad : {-1.0, std::nan("")}) {
      Material b;
      b.*band = bad;
      EXPECT_CONTAINS(testing::error_message<InputError>([&] { b.validate(); }), "must be >= 0");
    }
  Material vapor_band;
  vapor_band.latent_vapor = -1;
  EXPECT_EQ(testing::error_message<InputError>([&] { vapor_band.validate(); }),
            "material.latent_vapor = -1: must be >= 0");
}

TEST(ThermalInput, SpecAndStartStateChecked) {
  Particles p;
  p.add(Vec3::Zero(), 1e-4, 0, 300.0);
  ThermalSpec spec;
  spec.phi = 1.5;
  EXPECT_EQ(testing::error_message<InputError>([&] { ThermalModel(p, {Material{}}, spec); }),
            "thermal.phi = 1.5: must be in [0, 1]");
  spec = {};
  spec.solver = "gauss";
  EXPECT_CONTAINS(testing::error_message<InputError>([&] { ThermalModel(p, {Material{}}, spec); }),
                  "thermal.solver");
  p.material[0] = 2;
  EXPECT_CONTAINS(testing::error_message<InputError>([&] { ThermalModel(p, {Material{}}, {}); }),
                  "must be < 1");
  p.material[0] = 0;
  // A particle at theta_v or above would start as vapour: refused, from exactly theta_v up.
  for (const double start : {800.0, Material{}.vapor_temperature}) {
    p.temperature[0] = start;
    EXPECT_CONTAINS(testing::error_message<InputError>([&] { ThermalModel(p, {Material{}}, {}); }),
                    "must be < its material's vapor_temperature = 700 K (it would start as "
                    "vapour)");
  }
  p.temperature[0] = std::nextafter(Material{}.vapor_temperature, 0.0);  // just below: liquid
  ThermalModel liquid(p, {Material{}}, {});
  EXPECT_EQ(p.phase[0], Phase::liquid);
}

TEST(ThermalGraph, PairAverageConductivityByMaterial) {
  Particles p;
  p.add(Vec3::Zero(), 1e-4, 0);
  p.add(Vec3(1.5e-4, 0, 0), 1e-4, 1);
  p.add(Vec3(3.0e-4, 0, 0), 1e-4, 1);
  Material a, b;
  a.conductivity = 10;
  b.conductivity = 30;
  const auto contacts = find_contacts(p);
  ASSERT_EQ(contacts.size(), 2u);
  const auto g = contact_conductances(p, {a, b}, contacts);
  const ContactGeometry geo = contact_geometry(1.5e-4, 1e-4, 1e-4);
  EXPECT_DOUBLE_EQ(g[0], 20.0 * geo.area / geo.distance);  // (10 + 30) / 2
  EXPECT_DOUBLE_EQ(g[1], 30.0 * geo.area / geo.distance);
  // L + W is a graph Laplacian: symmetric, zero row sums without walls.
  const SparseMatrix l = conduction_matrix(p, contacts, g, {});
  EXPECT_NEAR((Eigen::MatrixXd(l) - Eigen::MatrixXd(l).transpose()).norm(), 0.0, 0.0);
  EXPECT_NEAR((Eigen::MatrixXd(l) * Eigen::Vector3d::Ones()).norm(), 0.0, 1e-18);
}

// A vaporised particle has left the graph: a contact still listed with it carries no heat, into
// or out of it. Three spheres in a row, the last removed: the flux (L theta)_i is the first
// contact's alone, whatever the removed one's temperature.
TEST(ThermalGraph, AContactWithARemovedParticleConductsNothing) {
  Particles p;
  p.add(Vec3::Zero(), 1e-4, 0);
  p.add(Vec3(1.5e-4, 0, 0), 1e-4, 0);
  p.add(Vec3(3.0e-4, 0, 0), 1e-4, 0);
  Material m;
  m.conductivity = 10;
  const auto contacts = find_contacts(p);  // before the removal: (0, 1) and (1, 2)
  ASSERT_EQ(contacts.size(), 2u);
  p.remove(2);
  const auto g = contact_conductances(p, {m}, contacts);
  const SparseMatrix l = conduction_matrix(p, contacts, g, {});
  const Eigen::VectorXd flux = l * Eigen::Vector3d(400.0, 300.0, 5000.0);
  EXPECT_DOUBLE_EQ(flux[0], g[0] * 100.0);
  EXPECT_DOUBLE_EQ(flux[1], -g[0] * 100.0);
  EXPECT_EQ(flux[2], 0.0);
}

TEST(ThermalGraph, WallsTouchOnlyParticlesWithinReach) {
  Particles p;
  p.add(Vec3(1.0e-4, 0, 0), 1e-4, 0);   // touches x = 0
  p.add(Vec3(1.05e-4, 0, 0), 1e-4, 0);  // 5 um off: within a reach of 1e-5
  p.add(Vec3(5e-4, 0, 0), 1e-4, 0);     // far
  Material m;
  m.conductivity = 7;
  const WallCoupling w = wall_coupling(p, {m}, {{0, 0.0, 1e-5, 250.0, -1.0}});
  EXPECT_DOUBLE_EQ(w.conductance[0], std::numbers::pi * 7 * 1e-4);
  EXPECT_DOUBLE_EQ(w.conductance[1], std::numbers::pi * 7 * 1e-4);
  EXPECT_EQ(w.conductance[2], 0.0);
  EXPECT_DOUBLE_EQ(w.source[0], 250.0 * w.conductance[0]);
}

// A lattice at L = 0.5 has a layer of spheres tangent to each face of the cube. With a reach of 0
// round-off decided which faces touched theirs: at n = 10, D = 1e-3 the x-, y- and z- walls
// touched 100 spheres each and the x+, y+ and z+ walls none (found by an audit).
TEST(ThermalGraph, EveryFaceTouchesTheLatticeLayerTangentToIt) {
  for (const auto& [n, size] : {std::pair{10, 1e-3}, std::pair{13, 3e-3}, std::pair{7, 1e-3}}) {
    const Particles p = lattice_packing(std::size_t(n * n * n), size, 0.5);
    for (int axis = 0; axis < 3; ++axis)
      for (double position : {0.0, size}) {
        const Wall wall{axis, position, 0.0, 300.0, -1.0};
        std::size_t touching = 0;
        for (std::size_t i = 0; i < p.size(); ++i) touching += touches(wall, p, i);
        EXPECT_EQ(touching, std::size_t(n * n))
            << "n = " << n << ", axis " << axis << " at " << position;
      }
  }
}

TEST(ThermalSkip, ZeroConductivityBuildsNoMatrixAndSolvesNothing) {
  Particles p = random_overlap_packing(300, 1e-3, 0.5, 2);
  ThermalModel model(p, {Material{}}, {});  // K = 0
  model.set_contacts(find_contacts(p));
  std::vector<double> dh(p.size(), 1e-12);
  const StepReport r = model.step(1e-9, dh);
  EXPECT_FALSE(r.conduction_ran);
  EXPECT_FALSE(r.phases_ran);
  EXPECT_EQ(r.solver, "none");
  EXPECT_EQ(r.iterations, 0);
  for (std::size_t i = 0; i < p.size(); ++i)
    EXPECT_NEAR(p.temperature[i], 300.0 + 1e-12 / model.thermal_mass(i), 1e-9);
}

// A conducting packing with random heating where the fixed-point iteration contracts.
struct AgreeScene {
  Particles p = random_overlap_packing(600, 1e-3, 0.45, 9);
  std::vector<double> dh;
  Material m;
  AgreeScene() {
    m.conductivity = 100;
    std::mt19937_64 rng(3);
    std::uniform_real_distribution<double> u(0.0, 2e-10);
    for (std::size_t i = 0; i < p.size(); ++i) dh.push_back(u(rng));
  }
};

double explicit_limit(AgreeScene& s) {
  ThermalSpec spec;
  spec.phi = 0;
  ThermalModel model(s.p, {s.m}, spec);
  model.set_contacts(find_contacts(s.p));
  return model.monotone_step_limit();
}

TEST(ThermalSolvers, AllThreeAgree) {
  std::vector<std::vector<double>> results;
  for (const char* solver : {"fixed-point", "cg", "direct", "auto"}) {
    AgreeScene s;
    ThermalSpec spec;
    spec.solver = solver;
    spec.phi = 0.5;
    spec.tolerance = 1e-13;
    ThermalModel model(s.p, {s.m}, spec);
    model.set_contacts(find_contacts(s.p));
    // The explicit limit min c/D makes the contraction dt phi max 2D/c = 0.05 here.
    const double dt = 0.05 * explicit_limit(s);
    StepReport r;
    for (int k = 0; k < 3; ++k) r = model.step(dt, s.dh);
    EXPECT_NEAR(r.contraction_estimate, 0.05, 1e-12);
    EXPECT_TRUE(r.conduction_ran);
    EXPECT_EQ(r.solver, std::string(solver) == "auto" ? "fixed-point" : solver);
    results.push_back(s.p.temperature);
  }
  double spread = 0;
  for (std::size_t i = 0; i < results[0].size(); ++i)
    for (const auto& r : results) spread = std::max(spread, std::abs(r[i] - results[2][i]));
  EXPECT_LT(spread, 1e-8);
}

// A deposit far below tolerance * c theta (temperatures count from 0 K) still reaches the
// temperatures, with every solver: two touching spheres at 300 K, one heated by d = 1e-5 K,
// one backward-Euler step with x = dt G / c. Exact: the heated one rises d (1 + x) / (1 + 2x),
// the other d x / (1 + 2x). Before the iterative solvers solved for the step's change, CG
// stopped at once (the heat was lost) and the fixed-point iteration after its first update.
TEST(ThermalSolvers, ADepositBelowToleranceTimesTemperatureIsNotLost) {
  for (const char* solver : {"fixed-point", "cg", "direct", "auto"}) {
    Particles p;
    p.add(Vec3(0, 0, 0), 1e-4, 0, 300.0);
    p.add(Vec3(1.5e-4, 0, 0), 1e-4, 0, 300.0);
    Material m;
    m.conductivity = 100;
    ThermalSpec spec;
    spec.solver = solver;
    spec.tolerance = 1e-6;
    ThermalModel model(p, {m}, spec);
    const std::vector<Contact> contacts = find_contacts(p);
    ASSERT_EQ(contacts.size(), 1u);
    model.set_contacts(contacts);
    const double c = model.thermal_mass(0), g = contact_conductances(p, {m}, contacts)[0];
    const double x = std::string(solver) == "fixed-point" ? 0.2 : 1.0;  // auto: CG (rho = 2)
    const double d = 1e-5;
    const StepReport r = model.step(x * c / g, {d * c, 0.0});
    EXPECT_EQ(r.solver, std::string(solver) == "auto" ? "cg" : solver);
    EXPECT_NEAR(p.temperature[0] - 300.0, d * (1 + x) / (1 + 2 * x), 1e-5 * d) << solver;
    EXPECT_NEAR(p.temperature[1] - 300.0, d * x / (1 + 2 * x), 1e-5 * d) << solver;
    EXPECT_NEAR(model.ledger().imbalance(), 0.0, 1e-5 * model.ledger().absorbed) << solver;
  }
}

// Heating alone never lowers a temperature, however small the deposit against the temperature:
// the diagonal step (K = 0) adds the change to theta0 (rises below 2e-14 K here, under the
// spacing of doubles near 300 K). (c theta0 + dH) / c rounded some of them below theta0.
TEST(ThermalSolvers, HeatingNeverRoundsATemperatureBelowItsStart) {
  std::mt19937_64 rng(9);
  std::uniform_real_distribution<double> u(0.0, 2e-14), radius(1e-5, 2e-5), start(300.0, 301.0);
  Particles p;
  for (int k = 0; k < 2000; ++k) p.add(Vec3(1e-4 * k, 0, 0), radius(rng), 0, start(rng));
  // Without walls, and with a wall at 1000 K out of every particle's reach but the first's (the
  // solve then measures temperatures from 1000 K: the round trip lost a bit for 1 in 7 of them).
  for (bool walls : {false, true}) {
    Particles q = p;
    ThermalSpec spec;
    if (walls) spec.walls = {{0, 0.0, 1e-6, 1000.0, 1e-9}};
    ThermalModel model(q, {Material{}}, spec);
    std::vector<double> dh(q.size());
    for (std::size_t i = 0; i < q.size(); ++i) dh[i] = u(rng) * model.thermal_mass(i);  // < 2e-14 K
    const StepReport r = model.step(1e-12, dh);
    EXPECT_EQ(r.solver, walls ? "diagonal" : "none");
    for (std::size_t i = 1; i < q.size(); ++i)
      ASSERT_GE(q.temperature[i], p.temperature[i]) << i << (walls ? " walls" : "");
  }
}

TEST(ThermalSolvers, DirectReusesSymbolicAnalysisWhileGraphUnchanged) {
  AgreeScene s;
  ThermalSpec spec;
  spec.solver = "direct";
  spec.skip_resting = false;  // the scene is at rest: skipping, nothing would be solved
  ThermalModel model(s.p, {s.m}, spec);
  model.set_contacts(find_contacts(s.p));
  StepReport r = model.step(1e-9, {});
  EXPECT_FALSE(r.symbolic_reused);
  r = model.step(1e-9, {});
  EXPECT_TRUE(r.symbolic_reused);
  EXPECT_TRUE(r.factors_reused);  // same dt, same phases: same matrix
  r = model.step(2e-9, {});
  EXPECT_TRUE(r.symbolic_reused);
  EXPECT_FALSE(r.factors_reused);
  model.set_contacts(find_contacts(s.p));  // same pattern
  EXPECT_TRUE(model.step(2e-9, {}).symbolic_reused);
  s.p.remove(0);
  model.set_contacts(find_contacts(s.p));  // new pattern
  EXPECT_FALSE(model.step(2e-9, {}).symbolic_reused);
}

// skip_resting: heat given to the particles near the face x = 0 of a 2000-sphere packing at
// 300 K (some walls); only the components it reaches, or that a wall at another temperature
// drives, are solved. Every temperature matches the whole system's solve to the solver
// tolerance, the others stay at exactly 300 K, and both ledgers close.
struct RestingScene {
  Particles p = random_overlap_packing(2000, 1e-3, 0.325, 11);
  std::vector<double> dh;
  Material m;
  explicit RestingScene(double heat, double conductivity = 100) {
    m.conductivity = conductivity;
    std::mt19937_64 rng(5);
    std::uniform_real_distribution<double> u(0.0, 1.0);
    for (std::size_t i = 0; i < p.size(); ++i)
      dh.push_back(p.centre[i].x() < 1e-4 ? heat * u(rng) : 0.0);
  }
};

struct RestingRun {
  std::vector<double> temperature;
  std::vector<std::uint32_t> vaporized;
  std::size_t solved = 0,
              live = 0;            // the most rows a step solved; live rows then (sub-steps summed)
  std::size_t live_particles = 0;  // at the end
  bool skipped = false;            // some step left rows out
  double imbalance = 0;
};

RestingRun run_resting(double heat, const ThermalSpec& base, bool skip, double conductivity = 100) {
  RestingScene s(heat, conductivity);
  ThermalSpec spec = base;
  spec.skip_resting = skip;
  ThermalModel model(s.p, {s.m}, spec);
  model.set_contacts(find_contacts(s.p));
  RestingRun r;
  for (int k = 0; k < 4; ++k) {
    for (std::size_t i = 0; i < s.dh.size(); ++i)
      if (!s.p.alive[i]) s.dh[i] = 0;  // the rays would no longer meet it
    const StepReport report = model.step(2e-10, k < 2 ? s.dh : std::vector<double>{});
    r.vaporized.insert(r.vaporized.end(), report.vaporized.begin(), report.vaporized.end());
    if (report.solved_rows >= r.solved) r.solved = report.solved_rows, r.live = report.live_rows;
    r.skipped |= report.solved_rows < report.live_rows;
  }
  r.temperature = s.p.temperature;
  r.live_particles = s.p.alive_count();
  r.imbalance = std::abs(model.ledger().imbalance()) / model.ledger().absorbed;
  return r;
}

struct ManyRowRun {
  std::vector<double> temperature;
  std::size_t solved = 0, live = 0;  // the first step's
};

// Three steps of a 4e4-sphere packing heated over a third of its depth, on `threads` threads.
ManyRowRun many_row_run(const Particles& start, const std::vector<Contact>& contacts, bool skip,
                        int threads) {
  Particles p = start;
  std::vector<double> dh(p.size(), 0.0);
  for (std::size_t i = 0; i < p.size(); ++i)
    if (p.centre[i].x() < 0.35e-3) dh[i] = 1e-13 * (1.0 + double(i % 7));
  Material m;
  m.conductivity = 100;
  ThermalSpec spec;
  spec.solver = "cg";
  spec.tolerance = 1e-13;
  spec.skip_resting = skip;
  ManyRowRun r;
  tbb::task_arena arena(threads);
  arena.execute([&] {
    ThermalModel model(p, {m}, spec);
    model.set_contacts(contacts);
    for (int k = 0; k < 3; ++k) {
      const StepReport report = model.step(2e-10, k < 2 ? dh : std::vector<double>{});
      if (k == 0) r.solved = report.solved_rows, r.live = report.live_rows;
    }
  });
  r.temperature = p.temperature;
  return r;
}

// Busy rows beyond the count at which their system is cut over threads (8192): the temperatures
// of the whole solve (to its tolerance), and the same bits on one thread and two.
TEST(ThermalSkip, AManyRowBusySystemMatchesTheWholeSolveOnAnyThreadCount) {
  const Particles start = random_overlap_packing(40000, 1e-3, 0.325, 3);
  const std::vector<Contact> contacts = find_contacts(start);
  const ManyRowRun one = many_row_run(start, contacts, true, 1),
                   two = many_row_run(start, contacts, true, 2),
                   whole = many_row_run(start, contacts, false, 2);
  ASSERT_GT(one.solved, 8192u * 3 / 2);
  ASSERT_LT(one.solved, one.live);  // the busy system, not the whole
  EXPECT_EQ(whole.solved, whole.live);
  std::size_t heated = 0;
  for (std::size_t i = 0; i < start.size(); ++i) {
    ASSERT_EQ(one.temperature[i], two.temperature[i]) << "particle " << i;
    ASSERT_NEAR(one.temperature[i], whole.temperature[i], 1e-9 * whole.temperature[i])
        << "particle " << i;
    heated += one.temperature[i] > 300.0;
  }
  EXPECT_GT(heated, 8192u);
}

TEST(ThermalSkip, RestingComponentsAreSkippedAndTheBusyOnesMatchTheWholeSolve) {
  for (double k : {100.0, 0.0})  // K = 0: every particle is its own component
    for (const char* solver : {"cg", "direct", "auto"})
      for (double phi : {1.0, 0.5})
        for (const char* walls : {"", "300", "450"})
          for (double heat :
               {5e-13, 1e-10}) {  // up to ~7 K a step; up to ~1400 K: melting, vaporising
            ThermalSpec spec;
            spec.solver = solver;
            spec.phi = phi;
            spec.tolerance = 1e-13;
            if (*walls) spec.walls = {Wall{2, 0.0, 2e-5, std::atof(walls), -1}};  // the face z = 0
            std::ostringstream name;
            name << "K " << k << " " << solver << " phi " << phi << " wall " << walls << " heat "
                 << heat;
            const RestingRun whole = run_resting(heat, spec, false, k),
                             busy = run_resting(heat, spec, true, k);
            EXPECT_FALSE(whole.skipped) << name.str();
            EXPECT_LT(busy.solved, busy.live / 2) << name.str();  // the skip happened
            EXPECT_GT(busy.solved, 0u) << name.str();
            EXPECT_EQ(busy.vaporized, whole.vaporized) << name.str();
            EXPECT_TRUE(heat < 1e-12 || !busy.vaporized.empty())
                << name.str();  // the phase rules ran
            std::size_t untouched = 0;
            for (std::size_t i = 0; i < whole.temperature.size(); ++i) {
              EXPECT_NEAR(busy.temperature[i], whole.temperature[i], 1e-8 * whole.temperature[i])
                  << name.str() << " particle " << i;
              untouched += busy.temperature[i] == 300.0;
            }
            EXPECT_GT(untouched, busy.live_particles / 2) << name.str();
            EXPECT_LT(busy.imbalance, 1e-9) << name.str();
            EXPECT_LT(whole.imbalance, 1e-9) << name.str();
          }
}

// After vaporisations the contact list is cut, not searched again: it equals a new search.
TEST(ThermalGraph, DroppingRemovedContactsEqualsANewSearch) {
  RestingScene s(1e-10);
  ThermalModel model(s.p, {s.m}, {});
  model.set_contacts(find_contacts(s.p));
  const std::size_t before = model.contacts().size();
  ASSERT_FALSE(model.step(2e-10, s.dh).vaporized.empty());
  model.drop_removed_contacts(0.0);
  const std::vector<Contact> found = find_contacts(s.p);
  ASSERT_LT(found.size(), before);
  ASSERT_EQ(model.contacts().size(), found.size());
  for (std::size_t e = 0; e < found.size(); ++e) {
    EXPECT_EQ(model.contacts()[e].i, found[e].i);
    EXPECT_EQ(model.contacts()[e].j, found[e].j);
    EXPECT_EQ(model.contacts()[e].area, found[e].area);
  }
}

// The contacts with a removed end, counted from the list and the live flags.
std::size_t removed_contacts(const ThermalModel& model, const Particles& p) {
  std::size_t n = 0;
  for (const Contact& c : model.contacts()) n += !p.alive[c.i] || !p.alive[c.j];
  return n;
}

// drop_removed_contacts cuts the list once its removed contacts reach the fraction asked, and not
// before, over vaporisations in several steps and after a restore brings particles back (it keeps
// a bound on them instead of looking at the list at every vaporisation).
TEST(ThermalGraph, RemovedContactsAreDroppedAtTheirThresholdOverSeveralSteps) {
  RestingScene s(0.0);
  std::vector<double> first(s.p.size(), 0.0), second(s.p.size(), 0.0);
  for (std::size_t i = 0; i < s.p.size(); ++i) {
    const double x = s.p.centre[i].x();
    (x < 5e-5 ? first : second)[i] = x < 1e-4 ? 1e-8 : 0.0;
  }
  ThermalModel model(s.p, {s.m}, {});
  model.set_contacts(find_contacts(s.p));
  const ThermalModel::Snapshot start = model.save();
  const double n = static_cast<double>(model.contacts().size());
  for (int pass = 0; pass < 2; ++pass) {  // the second after the restore
    ASSERT_FALSE(model.step(1e-10, first).vaporized.empty());
    const std::size_t after_first = removed_contacts(model, s.p);
    ASSERT_GT(after_first, 0u);
    model.drop_removed_contacts((double(after_first) + 0.5) / n);  // one short: kept
    EXPECT_EQ(removed_contacts(model, s.p), after_first) << "pass " << pass;
    std::vector<double> onto_live = second;  // conduction may have vaporised some already
    for (std::size_t i = 0; i < s.p.size(); ++i)
      if (!s.p.alive[i]) onto_live[i] = 0.0;
    ASSERT_FALSE(model.step(1e-10, onto_live).vaporized.empty());
    const std::size_t after_second = removed_contacts(model, s.p);
    ASSERT_GT(after_second, after_first + 1);
    model.drop_removed_contacts((double(after_second) - 0.5) / n);  // reached: cut
    EXPECT_EQ(removed_contacts(model, s.p), 0u) << "pass " << pass;
    EXPECT_EQ(double(model.contacts().size()), n - double(after_second)) << "pass " << pass;
    model.restore(start);
    model.set_contacts(find_contacts(s.p));  // every particle back, with its contacts
  }
  // A restore to a state with removed particles (a checkpoint's) after a look that found none.
  ASSERT_FALSE(model.step(1e-10, first).vaporized.empty());
  const ThermalModel::Snapshot removed = model.save();
  const std::size_t in_removed = removed_contacts(model, s.p);
  model.restore(start);
  model.drop_removed_contacts(0.0);  // none removed now
  ASSERT_EQ(double(model.contacts().size()), n);
  model.restore(removed);
  model.drop_removed_contacts((double(in_removed) - 0.5) / n);
  EXPECT_EQ(removed_contacts(model, s.p), 0u);
  EXPECT_EQ(double(model.contacts().size()), n - double(in_removed));
}

// A vaporisation (and its undoing by restore) updates the matrix in place; a new assembly from
// the cut contact list gives the same values up to explicit zeros, which CG's sums do not see:
// the temperatures agree bit for bit.
std::vector<double> vaporise_and_redo(bool assemble_anew) {
  RestingScene s(1e-10);
  ThermalSpec spec;
  spec.solver = "cg";
  spec.skip_resting = false;                       // every row solved: a wrong entry anywhere shows
  spec.walls = {Wall{0, 0.0, 1e-4, 350.0, 1e-6}};  // every heated particle touches it, weakly
  ThermalModel model(s.p, {s.m}, spec);
  model.set_contacts(find_contacts(s.p));
  const ThermalModel::Snapshot start = model.save();
  std::vector<double> out;
  for (int redo = 0; redo < 2; ++redo) {
    EXPECT_FALSE(model.step(2e-10, s.dh).vaporized.empty());
    if (assemble_anew) model.drop_removed_contacts(0.0);
    model.step(2e-10, {});
    out.insert(out.end(), s.p.temperature.begin(), s.p.temperature.end());
    model.restore(start);  // the vaporised particles live again
    if (assemble_anew) model.set_contacts(find_contacts(s.p));
  }
  return out;
}

TEST(ThermalGraph, UpdatingTheLiveSetInPlaceEqualsANewAssembly) {
  const std::vector<double> in_place = vaporise_and_redo(false), anew = vaporise_and_redo(true);
  ASSERT_EQ(in_place.size(), anew.size());
  for (std::size_t i = 0; i < in_place.size(); ++i) ASSERT_EQ(in_place[i], anew[i]) << i;
}

// A snapshot with one array short is refused whole: it left the particles' arrays of different
// lengths (only the temperatures' length was checked).
TEST(ThermalGraph, ASnapshotWithAShortArrayChangesNothing) {
  Particles p = random_overlap_packing(50, 1e-3, 0.325, 7);
  ThermalModel model(p, {Material{}}, ThermalSpec{});
  for (const int part : {0, 1, 2}) {
    ThermalModel::Snapshot s = model.save();
    if (part == 0) s.temperature.pop_back();
    if (part == 1) s.phase.pop_back();
    if (part == 2) s.alive.pop_back();
    EXPECT_THROW(model.restore(s), RunError) << part;
    EXPECT_EQ(p.temperature.size(), 50u);
    EXPECT_EQ(p.phase.size(), 50u);
    EXPECT_EQ(p.alive.size(), 50u);
  }
}

// Vaporisations split components and a redo joins them back; the model follows both in place,
// walking only the components concerned. Seeded: 40 random live sets in a row (a tenth of the
// particles vaporised or brought back each time, above the percolation threshold so a giant
// component breaks up), each against a model built afresh on the same live set.
TEST(ThermalGraph, ComponentsFollowVaporisationsAndRedosAsANewSearchFindsThem) {
  Particles p = random_overlap_packing(1500, 1e-3, 0.45, 7);  // ~3 neighbours each
  Material m;
  m.conductivity = 10;
  ThermalSpec spec;
  spec.walls = {Wall{2, 0.0, 5e-5, 300.0, -1}};  // the face z = 0: some components are walled
  const std::vector<Contact> contacts = find_contacts(p);
  ThermalModel model(p, {m}, spec);
  model.set_contacts(contacts);
  std::mt19937_64 rng(2013);
  std::size_t components = 0, largest = 0;  // summed over the rounds; the largest seen
  for (int round = 0; round < 40; ++round) {
    ThermalModel::Snapshot s = model.save();
    for (auto& alive : s.alive)
      if (std::uniform_real_distribution<>(0, 1)(rng) < 0.1) alive = !alive;
    model.restore(s);
    Particles fresh_p = p;
    ThermalModel fresh(fresh_p, {m}, spec);
    fresh.set_contacts(contacts);
    std::size_t roots = 0;
    for (std::size_t i = 0; i < p.size(); ++i) {
      if (!p.alive[i]) continue;
      ASSERT_EQ(model.component_of(i), fresh.component_of(i))
          << "round " << round << " particle " << i;
      ASSERT_EQ(model.in_insulated_cluster(i), fresh.in_insulated_cluster(i))
          << "round " << round << " particle " << i;
      roots += model.component_of(i) == i;
      std::size_t size = 0;
      if (model.component_of(i) == i)
        for (std::size_t j = 0; j < p.size(); ++j) size += p.alive[j] && model.component_of(j) == i;
      largest = std::max(largest, size);
    }
    components += roots;
  }
  EXPECT_GT(largest, 200u);  // a giant component was there to break up
  EXPECT_GT(components, 40u * 100);
}

// After its first step the model looks only at the components it solved last and at those given
// heat: it must pick the same rows as a look at every particle, step after step, through heating,
// cooling without heat, vaporisation, sub-steps and the stagger's redo of a step. The second
// model is made to look at every particle each step (a snapshot it did not take).
TEST(ThermalSkip, TheRestlessComponentsAreTheBusyOnesEveryParticleWouldShow) {
  for (double k : {100.0, 0.0})
    for (double phi : {1.0, 0.5})
      for (const char* walls : {"", "450"}) {
        std::ostringstream name;
        name << "K " << k << " phi " << phi << " wall " << walls;
        RestingScene a(1e-10, k), b(1e-10, k);
        ThermalSpec spec;
        spec.phi = phi;
        if (*walls) spec.walls = {Wall{2, 0.0, 2e-5, std::atof(walls), -1}};
        ThermalModel tracked(a.p, {a.m}, spec), looked(b.p, {b.m}, spec);
        tracked.set_contacts(find_contacts(a.p));
        looked.set_contacts(find_contacts(b.p));
        std::size_t vaporized = 0, skipped = 0;
        for (int step = 0; step < 12; ++step) {
          ThermalModel::Snapshot from_elsewhere = looked.save();
          from_elsewhere.serial = 0;
          looked.restore(from_elsewhere);
          const bool heat = step % 4 < 2;  // two steps heated, two cooling, ...
          for (std::size_t i = 0; i < a.dh.size(); ++i)
            if (!a.p.alive[i]) a.dh[i] = 0;
          const std::vector<double> dh = heat ? a.dh : std::vector<double>{};
          const ThermalModel::Snapshot before = tracked.save(), before_b = looked.save();
          StepReport ra = tracked.step(2e-10, dh), rb = looked.step(2e-10, dh);
          if (step == 5) {  // the stagger: the step undone and redone
            tracked.restore(before), looked.restore(before_b);
            ra = tracked.step(2e-10, dh), rb = looked.step(2e-10, dh);
          }
          ASSERT_EQ(ra.solved_rows, rb.solved_rows) << name.str() << " step " << step;
          ASSERT_EQ(ra.vaporized, rb.vaporized) << name.str() << " step " << step;
          ASSERT_EQ(a.p.temperature, b.p.temperature) << name.str() << " step " << step;
          vaporized += ra.vaporized.size();
          skipped += ra.solved_rows < ra.live_rows;
        }
        EXPECT_GT(vaporized, 0u) << name.str();
        EXPECT_GE(skipped, 10u) << name.str();
      }
}

// A snapshot of another model (or of a state other than now or before the last step) may hold
// components that are not at rest where this model's record says nothing is: after restoring
// it the model looks again.
TEST(ThermalSkip, ASnapshotFromElsewhereIsLookedAtWhole) {
  RestingScene a(5e-13), b(5e-13);
  ThermalModel warmed(a.p, {a.m}, {}), idle(b.p, {b.m}, {});
  warmed.set_contacts(find_contacts(a.p));
  idle.set_contacts(find_contacts(b.p));
  warmed.step(2e-10, a.dh);     // the heated components now differ inside
  idle.step(2e-10, {});         // nothing to do: its record holds no component
  idle.restore(warmed.save());  // the same step count, another model
  const StepReport ra = warmed.step(2e-10, {}), rb = idle.step(2e-10, {});
  EXPECT_GT(rb.solved_rows, 0u);
  EXPECT_EQ(ra.solved_rows, rb.solved_rows);
  EXPECT_EQ(a.p.temperature, b.p.temperature);
}

// The heat step told which particles were heated (in any order, with repeats) equals the one
// that finds them itself, and refuses a listed particle outside the deposits.
TEST(ThermalSkip, AListOfTheHeatedParticlesGivesTheSameStep) {
  RestingScene a(1e-10), b(1e-10);
  ThermalModel listed(a.p, {a.m}, {}), found(b.p, {b.m}, {});
  listed.set_contacts(find_contacts(a.p));
  found.set_contacts(find_contacts(b.p));
  std::vector<std::uint32_t> heated;
  for (std::size_t i = a.dh.size(); i-- > 0;)
    if (a.dh[i] != 0)
      heated.push_back(static_cast<std::uint32_t>(i)),
          heated.push_back(static_cast<std::uint32_t>(i));
  ASSERT_GT(heated.size(), 20u);
  for (int step = 0; step < 3; ++step) {
    const StepReport ra = listed.step(2e-10, a.dh, heated), rb = found.step(2e-10, b.dh);
    EXPECT_EQ(ra.vaporized, rb.vaporized);
    EXPECT_EQ(ra.solved_rows, rb.solved_rows);
    EXPECT_EQ(a.p.temperature, b.p.temperature);
    EXPECT_EQ(listed.ledger().absorbed, found.ledger().absorbed);
    for (std::uint32_t i : ra.vaporized) a.dh[i] = b.dh[i] = 0;
  }
  const std::vector<std::uint32_t> outside{static_cast<std::uint32_t>(a.p.size())};
  EXPECT_THROW(listed.step(2e-10, a.dh, outside), InputError);
}

// A step whose first sub-step is solved whole (most particles busy) and whose vaporisations
// leave the later ones busy: the whole solve moved resting chains by rounding, so the later
// sub-steps must look at every particle, as a model that always looks does (review finding).
TEST(ThermalSkip, SubStepsAfterAWholeSolveLookAtEveryParticle) {
  for (const char* solver : {"direct", "auto"}) {
    auto scene = [] {
      Particles p;
      std::mt19937_64 rng(3);
      std::uniform_real_distribution<double> u(0, 1);
      for (int k = 0; k < 10; ++k) {  // chains of four at rest, each at its own temperature
        const double t = 320 + 200 * u(rng);
        double x = 0;
        for (int j = 0; j < 4; ++j) {
          const double r = 1e-4 * (0.8 + 0.4 * u(rng));
          p.add(Vec3(x + r, k * 1e-2, 0), r, 0, t);
          x += 2 * r - 1e-5 * (1 + 3 * u(rng));
        }
      }
      for (int k = 0; k < 130; ++k) p.add(Vec3(5e-2, k * 1e-2, 0), 1e-4, 0, 300);  // to vaporise
      return p;
    };
    Particles a = scene(), b = scene();
    Material m;
    m.conductivity = 100;
    ThermalSpec spec;
    spec.phi = 0.5;
    spec.solver = solver;
    ThermalModel tracked(a, {m}, spec), looked(b, {m}, spec);
    tracked.set_contacts(find_contacts(a));
    looked.set_contacts(find_contacts(b));
    std::vector<double> heat(a.size(), 0.0);
    for (std::size_t i = 40; i < a.size(); ++i) heat[i] = 0.1;
    const double dt = 3.5 * tracked.monotone_step_limit();  // four sub-steps
    for (int step = 0; step < 4; ++step) {
      ThermalModel::Snapshot from_elsewhere = looked.save();
      from_elsewhere.serial = 0;
      looked.restore(from_elsewhere);
      const std::vector<double> dh = step == 1 ? heat : std::vector<double>{};
      const StepReport ra = tracked.step(dt, dh), rb = looked.step(dt, dh);
      EXPECT_EQ(ra.substeps, 4);
      EXPECT_EQ(ra.solved_rows, rb.solved_rows) << solver << " step " << step;
      EXPECT_EQ(a.temperature, b.temperature) << solver << " step " << step;
      if (step == 1) {
        EXPECT_EQ(ra.vaporized.size(), 130u);
      }
    }
  }
}

// save after a step, undo it, take another step from the same state, restore the snapshot: the
// restored state's busy components are not those of the step taken since (review finding).
TEST(ThermalSkip, RestoringTheUndoneBranchLooksAgain) {
  auto pairs = [] {
    Particles p;
    for (int k = 0; k < 10; ++k)
      p.add(Vec3(k * 1e-3, 0, 0), 1e-4), p.add(Vec3(k * 1e-3 + 1.8e-4, 0, 0), 1e-4);
    return p;
  };
  Particles a = pairs(), b = pairs();
  Material m;
  m.conductivity = 100;
  ThermalModel tracked(a, {m}, {}), fresh(b, {m}, {});
  tracked.set_contacts(find_contacts(a));
  fresh.set_contacts(find_contacts(b));
  std::vector<double> h0(a.size(), 0.0), h4(a.size(), 0.0);
  h0[0] = h4[4] = 1e-9;
  tracked.step(1e-9, {});
  tracked.step(1e-9, h0);  // pair {0, 1} now differs inside
  const ThermalModel::Snapshot branch = tracked.save();
  tracked.undo_step();
  tracked.step(1e-9, h4);  // another branch from the same state: pair {4, 5}
  tracked.restore(branch);
  fresh.restore(branch);
  const StepReport ra = tracked.step(1e-9, {}), rb = fresh.step(1e-9, {});
  EXPECT_EQ(rb.solved_rows, 2u);  // pair {0, 1}
  EXPECT_EQ(ra.solved_rows, rb.solved_rows);
  EXPECT_EQ(a.temperature, b.temperature);
}

// A wall away from the particles' temperature drives its components: not at rest.
TEST(ThermalSkip, AWallAtAnotherTemperatureKeepsItsComponentsBusy) {
  ThermalSpec cold, warm;
  cold.walls = {Wall{2, 0.0, 2e-5, 300.0, -1}};
  warm.walls = {Wall{2, 0.0, 2e-5, 450.0, -1}};
  EXPECT_GT(run_resting(5e-13, warm, true).solved, run_resting(5e-13, cold, true).solved);
}

TEST(ThermalState, RestoreRedoesAStepExactly) {
  Particles p;
  p.add(Vec3::Zero(), 1e-4, 0, 650.0);
  p.add(Vec3(1.5e-4, 0, 0), 1e-4, 0, 300.0);
  Material m;
  m.conductivity = 1;
  ThermalModel model(p, {m}, {});
  model.set_contacts(find_contacts(p));
  const auto snap = model.save();
  const std::vector<double> dh{10 * model.thermal_mass(0) * 100.0, 0.0};
  const StepReport first = model.step(1e-10, dh);
  ASSERT_EQ(first.vaporized.size(), 1u);
  const std::vector<double> t1 = p.temperature;
  const ThermalLedger l1 = model.ledger();
  model.restore(snap);
  EXPECT_EQ(p.alive[0], 1);
  EXPECT_EQ(p.phase[0], Phase::liquid);
  EXPECT_EQ(model.ledger().absorbed, 0.0);
  const StepReport again = model.step(1e-10, dh);
  EXPECT_EQ(again.vaporized, first.vaporized);
  EXPECT_EQ(p.temperature, t1);
  EXPECT_EQ(model.ledger().vaporized, l1.vaporized);
}

// The stagger undoes a step from what it changed: the same state as a full snapshot restored,
// through melting, vaporisation and Crank-Nicolson's sub-steps, and the redone step is the same.
TEST(ThermalState, UndoingAStepEqualsRestoringItsSnapshot) {
  for (double phi : {1.0, 0.5}) {
    RestingScene a(1e-10), b(1e-10);
    ThermalSpec spec;
    spec.phi = phi;  // 0.5: 80 sub-steps, the live set reassembled after a vaporisation in one
    spec.walls = {Wall{0, 0.0, 1e-4, 350.0, 1e-6}};  // every heated particle touches it, weakly
    ThermalModel undone(a.p, {a.m}, spec), restored(b.p, {b.m}, spec);
    undone.set_contacts(find_contacts(a.p));
    restored.set_contacts(find_contacts(b.p));
    EXPECT_THROW(undone.undo_step(), RunError);
    undone.step(2e-10, a.dh), restored.step(2e-10, b.dh);  // melts and vaporises
    for (std::size_t i = 0; i < a.dh.size(); ++i)
      if (!a.p.alive[i]) a.dh[i] = b.dh[i] = 0;  // the rays would no longer meet it
    const ThermalModel::Snapshot snap = restored.save();
    const StepReport first = undone.step(2e-10, a.dh);
    restored.step(2e-10, b.dh);
    ASSERT_FALSE(first.vaporized.empty());
    ASSERT_FALSE(first.phase_changed.empty());
    for (std::size_t i : first.phase_changed) EXPECT_NE(undone.phase_before_step(i), a.p.phase[i]);
    undone.undo_step();
    restored.restore(snap);
    EXPECT_THROW(undone.undo_step(), RunError);  // once per step
    EXPECT_EQ(a.p.temperature, b.p.temperature);
    EXPECT_EQ(a.p.phase, b.p.phase);
    EXPECT_EQ(a.p.alive, b.p.alive);
    EXPECT_EQ(undone.ledger().stored, restored.ledger().stored);
    EXPECT_EQ(undone.ledger().vaporized, restored.ledger().vaporized);
    EXPECT_EQ(undone.ledger().absorbed, restored.ledger().absorbed);
    const StepReport again = undone.step(2e-10, a.dh), other = restored.step(2e-10, b.dh);
    EXPECT_EQ(again.vaporized, first.vaporized);
    EXPECT_EQ(again.vaporized, other.vaporized);
    EXPECT_EQ(a.p.temperature, b.p.temperature);
    EXPECT_EQ(undone.ledger().imbalance(), restored.ledger().imbalance());
  }
}

// A step refused for its input leaves nothing to undo: undo_step must not take back the step
// before it (review finding).
TEST(ThermalState, ARefusedStepLeavesNothingToUndo) {
  RestingScene a(5e-13);
  ThermalModel model(a.p, {a.m}, {});
  model.set_contacts(find_contacts(a.p));
  model.step(2e-10, a.dh);
  const std::vector<double> warmed = a.p.temperature;
  std::vector<double> negative = a.dh;
  negative[0] = -1;
  EXPECT_THROW(model.step(2e-10, negative), InputError);  // the caller's input, not a failed run
  EXPECT_THROW(model.undo_step(), RunError);
  EXPECT_EQ(a.p.temperature, warmed);
}

// A step whose solver fails leaves the model as it was before the step, and nothing to undo;
// a step after it is the step a model that never saw the failure takes. The failure comes in the
// second of three sub-steps (phi = 1/4): the first melts the heated sphere, and its liquid
// capacity, a twentieth of the solid's, makes the fixed-point iteration contract twenty times
// more slowly (the liquid sub-step needs more than the 10 iterations allowed, the solid one fewer).
TEST(ThermalState, AStepWhoseSolverFailsChangesNothing) {
  auto pair = [] {
    Particles p;
    p.add(Vec3(0, 0, 0), 1e-4, 0, 590.0);
    p.add(Vec3(1.5e-4, 0, 0), 1e-4, 0, 300.0);
    return p;
  };
  Material m;
  m.conductivity = 100;
  m.c_liquid = 0.05 * m.c_solid;
  m.vapor_temperature = 1e5;
  ThermalSpec spec;
  spec.solver = "fixed-point";
  spec.phi = 0.25;
  spec.max_iterations = 10;
  Particles p = pair(), q = pair();
  ThermalModel model(p, {m}, spec), reference(q, {m}, spec);
  model.set_contacts(find_contacts(p)), reference.set_contacts(find_contacts(q));
  const double limit = model.monotone_step_limit(), c = model.thermal_mass(0);
  model.step(0.1 * limit, {}), reference.step(0.1 * limit, {});
  const std::vector<double> before = p.temperature;
  const ThermalLedger ledger = model.ledger();
  const auto failing_step = [&] { model.step(2.5 * limit, {200.0 * c, 0.0}); };
  testing::expect_error<RunError>(failing_step, "did not converge");
  EXPECT_EQ(p.temperature, before);
  EXPECT_EQ(p.phase[0], Phase::solid);
  EXPECT_EQ(model.ledger().absorbed, ledger.absorbed);
  EXPECT_EQ(model.ledger().stored, ledger.stored);
  EXPECT_THROW(model.undo_step(), RunError);
  model.step(0.1 * limit, {1e-3 * c, 0.0}), reference.step(0.1 * limit, {1e-3 * c, 0.0});
  EXPECT_EQ(p.temperature, q.temperature);
  EXPECT_EQ(model.ledger().stored, reference.ledger().stored);
}

TEST(ThermalLong, LongLedgerOnLargePacking) {
  if (!beampack::test::long_tests_asked()) GTEST_SKIP() << "set BEAMPACK_LONG=1";
  Particles p = random_overlap_packing(100000, 1e-3, 0.325, 1);
  Material m;
  m.conductivity = 100;
  ThermalModel model(p, {m}, {});
  model.set_contacts(find_contacts(p));
  std::vector<double> dh(p.size(), 0.0);
  for (std::size_t i = 0; i < p.size(); i += 7) dh[i] = 50.0 * model.thermal_mass(i);
  std::size_t vaporized = 0;
  for (int s = 0; s < 20; ++s) {
    for (std::size_t i = 0; i < p.size(); ++i)
      if (!p.alive[i]) dh[i] = 0;  // the ray scene no longer holds vapour
    vaporized += model.step(1e-12, dh).vaporized.size();
  }
  EXPECT_GT(vaporized, 0u);
  EXPECT_NEAR(model.ledger().imbalance(), 0.0, 1e-9 * model.ledger().absorbed);
}

}  // namespace
}  // namespace beampack
