// Phase change by latent-heat bands (paper, section 4; MODEL.md section 5 step 3), vaporisation
// and the energy ledger.
#include <gtest/gtest.h>

#include <random>

#include "geometry/contact.h"
#include "geometry/error.h"
#include "geometry/packing.h"
#include "tests/thermal_test_util.h"
#include "thermal/thermal_model.h"

namespace beampack {
namespace {

constexpr double kRadius = 1e-4;
constexpr double kScaling = 1e6;

// m / M of the test sphere: C_eff times this is the scaled thermal mass.
double mass_over_m(const Material& m) {
  return m.density * 4.0 / 3.0 * std::numbers::pi * std::pow(kRadius, 3) / kScaling;
}

// Distinct latent bands (J/(kg K)), so that a band applied in place of another changes the answer.
Material distinct_bands() {
  Material m;
  m.latent_melt = 1000;
  m.latent_solidify = 3000;
  m.latent_vapor = 5000;
  return m;
}

struct Single {
  Particles p;
  Material m;
  ThermalModel model;
  explicit Single(double theta0, ThermalSpec spec = {}, Material material = {})
      : p([&] {
          Particles q;
          q.add(Vec3::Zero(), kRadius, 0, theta0);
          return q;
        }()),
        m(material),
        model(p, {m}, spec) {}
};

TEST(ThermalPhase, ThroughMeltAndVaporInOneStepVaporisesWithBothBands) {
  Single s(300.0, {}, distinct_bands());
  const Material& m = s.m;
  // C_eff = C_S + dP_SL + dP_LV = 1000 + 1000 + 5000 = 7000 J/(kg K).
  const double c_eff = mass_over_m(m) * 7000.0;
  const double dh = c_eff * 500.0;  // 300 -> 800 K with both bands: beyond theta_v = 700
  const StepReport r = s.model.step(1e-9, {dh});
  ASSERT_EQ(r.vaporized, std::vector<std::uint32_t>{0});
  EXPECT_TRUE(r.phases_ran);
  EXPECT_GT(r.phases_seconds, 0.0);  // timed apart from the heat step (the phases stage)
  EXPECT_TRUE(r.phase_corrected);
  EXPECT_FALSE(r.conduction_ran);
  EXPECT_EQ(s.p.alive[0], 0);
  EXPECT_EQ(s.p.phase[0], Phase::vapor);
  EXPECT_NEAR(s.p.temperature[0], 800.0, 1e-9);
  // The vapour carries everything it absorbed; nothing is stored any more.
  EXPECT_NEAR(s.model.ledger().vaporized, dh, 1e-12 * dh);
  EXPECT_NEAR(s.model.ledger().stored, 0.0, 1e-12 * dh);
  EXPECT_NEAR(s.model.ledger().imbalance(), 0.0, 1e-12 * dh);
  EXPECT_EQ(r.bands_short, 0u);  // both crossings made
  EXPECT_EQ(r.band_heat_short, 0.0);
  EXPECT_TRUE(r.phase_changed.empty());  // live particles only: it left, with no optics to change
}

TEST(ThermalPhase, BandsHoldBackVaporisation) {
  // Enough to vaporise with C_S alone (predictor: 300 + 7 * 350 = 2750 K), not with both bands
  // (corrector, C_eff = 1000 + 1000 + 5000 = 7000): the particle ends liquid at 300 + 350 = 650 K.
  Single s(300.0, {}, distinct_bands());
  const Material& m = s.m;
  const double dh = mass_over_m(m) * 7000.0 * 350.0;
  const StepReport r = s.model.step(1e-9, {dh});
  EXPECT_TRUE(r.vaporized.empty());
  ASSERT_EQ(r.phase_changed, std::vector<std::uint32_t>{0});
  EXPECT_EQ(s.p.phase[0], Phase::liquid);
  EXPECT_NEAR(s.p.temperature[0], 650.0, 1e-9);
  EXPECT_NEAR(s.model.ledger().stored, dh, 1e-12 * dh);
  // The vapour band was charged for a crossing of theta_v the step no longer makes: 5000 J/(kg K)
  // over its 350 K.
  EXPECT_EQ(r.bands_short, 1u);
  EXPECT_NEAR(r.band_heat_short, mass_over_m(m) * 5000.0 * 350.0, 1e-12 * dh);
}

TEST(ThermalPhase, MeltingUsesSolidPlusMeltBand) {
  Single s(550.0, {}, distinct_bands());
  const Material& m = s.m;
  // Predictor 680 K: crosses theta_m only. Corrector C_eff = C_S + dP_SL = 2000: 550 + 130 / 2 =
  // 615 K, liquid (with the vapour band's 5000 instead it would stay solid at 571.7 K).
  const double dh = mass_over_m(m) * m.c_solid * 130.0;
  const StepReport r = s.model.step(1e-9, {dh});
  ASSERT_EQ(r.phase_changed, std::vector<std::uint32_t>{0});
  EXPECT_EQ(s.p.phase[0], Phase::liquid);
  EXPECT_NEAR(s.p.temperature[0], 615.0, 1e-9);
}

// Each particle changes phase at its own material's temperatures, with its own bands: two
// spheres apart, at 550 K, the same heat (m C_S 130 / M, a predicted 680 K). Material 0 melts at
// 600 K: corrected with C_S + dP_SL = 2000 to 615 K, liquid. Material 1 melts at 700 K: 680 K,
// solid, no band. With material 0's temperatures for both, the second would melt too.
TEST(ThermalPhase, EachParticleMeltsAtItsOwnMaterialsTemperature) {
  Particles p;
  p.add(Vec3::Zero(), kRadius, 0, 550.0);
  p.add(Vec3(1e-3, 0, 0), kRadius, 1, 550.0);
  Material low = distinct_bands(), high = distinct_bands();
  high.melt_temperature = 700;
  high.vapor_temperature = 900;
  ThermalModel model(p, {low, high}, {});
  const double dh = mass_over_m(low) * low.c_solid * 130.0;
  const StepReport r = model.step(1e-9, {dh, dh});
  EXPECT_EQ(r.phase_changed, std::vector<std::uint32_t>{0});
  EXPECT_EQ(p.phase[0], Phase::liquid);
  EXPECT_NEAR(p.temperature[0], 615.0, 1e-9);
  EXPECT_EQ(p.phase[1], Phase::solid);
  EXPECT_NEAR(p.temperature[1], 680.0, 1e-9);
}

// MODEL.md 5 step 3: a liquid crossing theta_v upward is re-solved with C = C_L + dP_LV/dtheta.
// Liquid at 650 K, dH = m C_L 80 / M: predictor 730 K >= theta_v = 700 K; corrector with
// C_eff = 2000 + 5000 = 7000: 650 + 80 * 2000 / 7000 = 672.857 K, below theta_v, so it stays
// liquid (the band of a predicted crossing stands, as for melting). No melt band: it starts liquid.
TEST(ThermalPhase, LiquidCrossingVaporAloneUsesLiquidPlusVaporBand) {
  Single s(650.0, {}, distinct_bands());
  const Material& m = s.m;
  ASSERT_EQ(s.p.phase[0], Phase::liquid);
  const double dh = mass_over_m(m) * 2000.0 * 80.0;
  const StepReport r = s.model.step(1e-9, {dh});
  EXPECT_TRUE(r.phase_corrected);
  EXPECT_TRUE(r.vaporized.empty());
  EXPECT_TRUE(r.phase_changed.empty());
  EXPECT_EQ(s.p.alive[0], 1);
  EXPECT_EQ(s.p.phase[0], Phase::liquid);
  EXPECT_NEAR(s.p.temperature[0], 650.0 + 80.0 * 2000.0 / 7000.0, 1e-9);
  // The ledger stores what the corrector's capacity took: m C_eff / M * 22.857 K = dH.
  EXPECT_NEAR(s.model.ledger().stored, dh, 1e-12 * dh);
}

TEST(ThermalPhase, BandOfAPredictedCrossingStaysEvenIfTheCorrectorFallsShort) {
  // Paper, section 4: the step that the predictor sees crossing theta_m is re-solved with
  // C_S + dP/dtheta and the result stands, even below theta_m (the band spreads the latent heat).
  Single s(550.0);
  const Material& m = s.m;
  const double dh = mass_over_m(m) * m.c_solid * 80.0;  // predictor 630 K, corrector 590 K
  const StepReport r = s.model.step(1e-9, {dh});
  EXPECT_TRUE(r.phase_corrected);
  EXPECT_TRUE(r.phase_changed.empty());
  EXPECT_EQ(s.p.phase[0], Phase::solid);
  EXPECT_NEAR(s.p.temperature[0], 590.0, 1e-9);
  EXPECT_NEAR(s.model.ledger().stored, dh, 1e-12 * dh);
  // Counted as a band charged for a melting that did not happen: dP_SL over the step's 40 K.
  EXPECT_EQ(r.bands_short, 1u);
  EXPECT_NEAR(r.band_heat_short, mass_over_m(m) * m.latent_melt * 40.0, 1e-12 * dh);
}

TEST(ThermalPhase, LiquidHeatsWithLiquidCapacity) {
  Single s(620.0);
  EXPECT_EQ(s.p.phase[0], Phase::liquid);  // set from the temperature at construction
  const double dh = mass_over_m(s.m) * s.m.c_liquid * 30.0;
  const StepReport r = s.model.step(1e-9, {dh});
  EXPECT_TRUE(r.phases_ran);
  EXPECT_FALSE(r.phase_corrected);
  EXPECT_TRUE(r.phase_changed.empty());
  EXPECT_NEAR(s.p.temperature[0], 650.0, 1e-9);
  EXPECT_NEAR(s.model.thermal_mass(0), mass_over_m(s.m) * s.m.c_liquid, 1e-24);
}

// Exactly at theta_m a particle is liquid (MODEL.md 5: "at or above theta_m"): C_L, no band.
TEST(ThermalPhase, AParticleExactlyAtMeltIsLiquid) {
  Single s(600.0);
  ASSERT_EQ(s.m.melt_temperature, 600.0);
  EXPECT_EQ(s.p.phase[0], Phase::liquid);
  s.model.step(1e-9, {mass_over_m(s.m) * s.m.c_liquid * 10.0});
  EXPECT_NEAR(s.p.temperature[0], 610.0, 1e-9);
}

TEST(ThermalPhase, CoolingThroughMeltSolidifiesWithLiquidPlusSolidifyBand) {
  // A liquid sphere against a cold wall, backward Euler: (c_eff + dt g) theta1 = c_eff theta0 +
  // dt g theta_w with c_eff = m (C_L + dP_LS / dtheta) / M once the predictor crosses theta_m.
  // From exactly theta_m too: liquid there (at or above theta_m), so its cooling crosses the band.
  for (const double start : {610.0, 600.0}) {
    ThermalSpec spec;
    const double g = 1e-3;  // W/K
    spec.walls.push_back({0, 0.0, 0.0, 300.0, g});
    Material solidifying;
    solidifying.latent_solidify = 3000;  // not latent_melt's 1000: the band must be this one
    Single s(start, spec, solidifying);
    const Material& m = s.m;
    ASSERT_EQ(s.p.phase[0], Phase::liquid) << start;
    const double dt = 0.5 * mass_over_m(m) * m.c_liquid / g;  // predictor: 610 -> ~506 K
    const StepReport r = s.model.step(dt, {});
    EXPECT_EQ(r.solver, "diagonal");
    ASSERT_EQ(r.phase_changed, std::vector<std::uint32_t>{0}) << start;
    EXPECT_EQ(s.p.phase[0], Phase::solid);
    const double c_eff = mass_over_m(m) * (m.c_liquid + m.latent_solidify);
    const double expected = (c_eff * start + dt * g * 300.0) / (c_eff + dt * g);
    EXPECT_NEAR(s.p.temperature[0], expected, 1e-9) << start;
    ASSERT_LT(expected, m.melt_temperature);
    // Everything that left the sphere went into the wall.
    EXPECT_NEAR(s.model.ledger().walls, -s.model.ledger().stored,
                1e-12 * std::abs(s.model.ledger().walls));
    EXPECT_NEAR(s.model.ledger().walls, c_eff * (start - expected), 1e-12 * s.model.ledger().walls);
  }
}

// A band one pass adds can push a neighbour across another: a liquid sphere at 640 K touching a
// solid one at 510 K (equal masses, a step long enough to equalise, dt G / c ~ 1e5). Predictor,
// C_L = 2000 and C_S = 1000: both go to (2000 640 + 1000 510) / 3000 = 596.7 K, the liquid
// crosses theta_m = 600 K downward. Pass 1, with its solidification band (C = 3000): both go to
// (3000 640 + 1000 510) / 4000 = 607.5 K, now the solid one crosses upward: a new band. Pass 2,
// with its melt band (C = 2000): (3000 640 + 2000 510) / 5000 = 588 K, no new band. With one
// pass allowed the step stops with the new band unsolved, and says so.
TEST(ThermalPhase, ACorrectorStoppedAtItsCapWithANewBandSaysSo) {
  for (const int cap : {1, 4}) {
    Particles p;
    p.add(Vec3::Zero(), kRadius, 0, 640.0);
    p.add(Vec3(1.5 * kRadius, 0, 0), kRadius, 0, 510.0);
    Material m;
    m.conductivity = 1.0;
    ThermalSpec spec;
    spec.max_phase_corrections = cap;
    ThermalModel model(p, {m}, spec);
    model.set_contacts(find_contacts(p));
    ASSERT_EQ(p.phase[0], Phase::liquid);
    const StepReport r = model.step(4e-3, {0.0, 0.0});
    EXPECT_TRUE(r.phase_corrected) << cap;
    EXPECT_EQ(r.phase_passes_capped, cap == 1) << cap;
    const double expected = cap == 1 ? 607.5 : 588.0;
    EXPECT_NEAR(p.temperature[0], expected, 0.05) << cap;
    EXPECT_NEAR(p.temperature[1], expected, 0.05) << cap;
  }
}

TEST(ThermalPhase, VaporisedParticleCarriesItsEnergyAndLeavesTheGraph) {
  // Two touching spheres; the first is heated until it vaporises. Its energy leaves the stored
  // column for the vaporised one, and the second no longer exchanges heat with it.
  Particles p;
  p.add(Vec3::Zero(), kRadius, 0, 300.0);
  p.add(Vec3(1.5 * kRadius, 0, 0), kRadius, 0, 300.0);
  Material m;
  m.conductivity = 1.0;
  ThermalModel model(p, {m}, {});
  model.set_contacts(find_contacts(p));
  const double c = model.thermal_mass(0);
  const double dh = 60.0 * c, dt = 4e-10;  // dt G / c ~ 0.01: the neighbour lags behind
  int steps = 0;
  while (p.alive[0] && steps < 200) {
    const StepReport r = model.step(dt, {dh, 0.0});
    ++steps;
    if (!p.alive[0]) {
      EXPECT_EQ(r.vaporized, std::vector<std::uint32_t>{0});
    }
  }
  ASSERT_EQ(p.alive[0], 0) << "did not vaporise in " << steps << " steps";
  const ThermalLedger& l = model.ledger();
  EXPECT_NEAR(l.absorbed, steps * dh, 1e-12 * l.absorbed);
  EXPECT_GT(l.vaporized, 0.5 * l.absorbed);
  EXPECT_NEAR(l.imbalance(), 0.0, 1e-9 * l.absorbed);
  // What remains stored is exactly the second sphere's heat.
  EXPECT_NEAR(l.stored, model.thermal_mass(1) * (p.temperature[1] - 300.0), 1e-9 * l.absorbed);
  const double theta1 = p.temperature[1];
  const StepReport after = model.step(dt, {0.0, 0.0});
  EXPECT_EQ(p.temperature[1], theta1);                 // no exchange with the vapour
  EXPECT_FALSE(after.conduction_ran);                  // no live contact conducts any more
  EXPECT_THROW(model.step(dt, {1.0, 0.0}), RunError);  // energy into vapour is a driver bug
}

// A step split into sub-steps (phi = 0 beyond its limit) whose first sub-step vaporises the
// heated sphere: the heat aimed at it in the later sub-steps leaves with the vapour. Stored is
// then exactly the neighbour's heat, vaporised the rest. The heated sphere starts at 590 K, solid
// just below theta_m, the neighbour at 300 K: the explicit first sub-step conducts on the
// starting temperatures, G (590 - 300) over dt / 5 = 0.9 c / G, so the neighbour ends at exactly
// 300 + 0.9 x 290 = 561 K (from equal temperatures it would not warm at all, and the ledger's
// split between stored and vaporised would be 0 and everything, whatever conduction did).
TEST(ThermalPhase, HeatForASphereVaporisedInAnEarlierSubStepLeavesWithIt) {
  ThermalSpec spec;
  spec.phi = 0;
  Particles p;
  p.add(Vec3::Zero(), kRadius, 0, 590.0);
  p.add(Vec3(1.5 * kRadius, 0, 0), kRadius, 0, 300.0);
  Material m;
  m.conductivity = 1e-3;
  ThermalModel model(p, {m}, spec);
  const auto contacts = find_contacts(p);
  model.set_contacts(contacts);
  ASSERT_EQ(p.phase[0], Phase::solid);
  const double dh = 1e3 * mass_over_m(m) * m.c_liquid * 400.0;  // vaporises it in one sub-step
  const double dt = 4.5 * model.monotone_step_limit();
  const StepReport r = model.step(dt, {dh, 0.0});
  ASSERT_EQ(r.substeps, 5);
  ASSERT_FALSE(p.alive[0]);
  const double g = contact_conductances(p, {m}, contacts)[0];
  const double c = mass_over_m(m) * m.c_solid;
  EXPECT_NEAR(p.temperature[1], 300.0 + dt / r.substeps * g * 290.0 / c, 1e-9);
  EXPECT_NEAR(p.temperature[1], 561.0, 1e-9);  // the limit is c / G: C_S < C_L
  const double neighbour = mass_over_m(m) * m.c_solid * (p.temperature[1] - 300.0);
  EXPECT_NEAR(model.ledger().stored, neighbour, 1e-9 * dh);
  EXPECT_NEAR(model.ledger().vaporized, dh - neighbour, 1e-9 * dh);
}

TEST(ThermalPhase, NoParticleNearMeltMeansNoPhaseWork) {
  Single s(300.0);
  const StepReport r = s.model.step(1e-9, {mass_over_m(s.m) * s.m.c_solid * 10.0});
  EXPECT_FALSE(r.phases_ran);
  EXPECT_EQ(r.phases_seconds, 0.0);  // the phases stage is charged nothing
  EXPECT_EQ(r.solver, "none");
  EXPECT_NEAR(s.p.temperature[0], 310.0, 1e-9);
}

// The ledger on a conducting packing with walls, random sources, Crank-Nicolson, melting and
// vaporisation: absorbed = stored + vaporized + walls to the solver tolerance.
TEST(ThermalLedger, ClosesOnPackingWithWallsAndVaporisation) {
  Particles p = random_overlap_packing(500, 1e-3, 0.4, 3);
  Material m;
  m.conductivity = 20;
  ThermalSpec spec;
  spec.phi = 0.5;
  spec.solver = "cg";
  spec.tolerance = 1e-12;
  spec.walls.push_back({0, 0.0, 1e-5, 300.0, -1.0});
  spec.walls.push_back({0, 1e-3, 1e-5, 280.0, -1.0});
  ThermalModel model(p, {m}, spec);
  model.set_contacts(find_contacts(p));
  std::mt19937_64 rng(5);
  std::uniform_real_distribution<double> u(0.0, 1.0);
  const double c = model.thermal_mass(0);
  const double dt = 1e-9;
  std::size_t vaporized = 0, melted = 0;
  for (int s = 0; s < 30; ++s) {
    std::vector<double> dh(p.size(), 0.0);
    for (std::size_t i = 0; i < p.size(); ++i)
      if (p.alive[i] && p.centre[i].x() < 3e-4) dh[i] = 40.0 * c * u(rng);
    const StepReport r = model.step(dt, dh);
    vaporized += r.vaporized.size();
    melted += r.phase_changed.size();
    if (!r.vaporized.empty()) model.set_contacts(find_contacts(p));
  }
  const ThermalLedger& l = model.ledger();
  EXPECT_GT(vaporized, 0u);
  EXPECT_GT(melted, 0u);
  EXPECT_GT(std::abs(l.walls), 1e-6 * l.absorbed);  // the walls do take heat
  EXPECT_NEAR(l.imbalance(), 0.0, 1e-9 * l.absorbed);
}

}  // namespace
}  // namespace beampack
