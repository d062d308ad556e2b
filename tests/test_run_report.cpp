// What a run reports beyond its figures: the warning when a ledger is open.
#include <gtest/gtest.h>

#include <limits>

#include "tools/run_command.h"

namespace beampack::tools {
namespace {

EnergyLedger closed_ledger() {
  EnergyLedger e;
  e.injected = 1.0, e.absorbed = 0.6, e.escaped = 0.3, e.cutoff = 0.1;
  e.stored = 0.5, e.vaporized = 0.1;
  return e;
}

TEST(RunReport, AClosedLedgerGivesNoWarning) {
  EXPECT_TRUE(open_ledger_warnings(SimulationSpec{}, closed_ledger()).empty());
  EnergyLedger round_off = closed_ledger();
  round_off.escaped += 1e-15, round_off.stored += 1e-12;  // round-off and a 1e-10 solver's error
  EXPECT_TRUE(open_ledger_warnings(SimulationSpec{}, round_off).empty());
}

TEST(RunReport, AnOpenLedgerIsNamedWithItsSize) {
  EnergyLedger optics = closed_ledger();
  optics.escaped -= 1e-6;
  const auto o = open_ledger_warnings(SimulationSpec{}, optics);
  ASSERT_EQ(o.size(), 1u);
  EXPECT_NE(o[0].find("optics ledger is open by 1e-06"), std::string::npos) << o[0];
  EnergyLedger heat = closed_ledger();
  heat.stored = 0.0;  // the stiff-wall case before the fix: the absorbed heat in no bin
  const auto h = open_ledger_warnings(SimulationSpec{}, heat);
  ASSERT_EQ(h.size(), 1u);
  EXPECT_NE(h[0].find("heat ledger is open by 0.833"), std::string::npos) << h[0];
  // A loose solver tolerance widens what counts as closed: 1e-3 of the absorbed at 1e-4.
  SimulationSpec loose;
  loose.thermal.tolerance = 1e-4;
  EnergyLedger slightly = closed_ledger();
  slightly.stored += 6e-4;
  EXPECT_TRUE(open_ledger_warnings(loose, slightly).empty());
  EXPECT_EQ(open_ledger_warnings(SimulationSpec{}, slightly).size(), 1u);
  EnergyLedger nan = closed_ledger();
  nan.walls = std::numeric_limits<double>::quiet_NaN();
  EXPECT_EQ(open_ledger_warnings(SimulationSpec{}, nan).size(), 1u);
}

}  // namespace
}  // namespace beampack::tools
