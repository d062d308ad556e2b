// What `beampack validate` and its stability grid accept: the analytic cases pass and cover what
// they claim; the grid refuses only for the reasons it expects and fails solvers that disagree.
#include <gtest/gtest.h>

#include <cmath>
#include <string>

#include "expect_error.h"
#include "tools/stability.h"
#include "tools/validate.h"

using namespace beampack;
using namespace beampack::tools;

namespace {

// Every case passes, and the ones that cover the beam's position and profile, unequal contact
// radii and the complex index off the normal are among them (a name changed is a case lost).
TEST(ValidateCases, AllPassAndCoverWhatTheyClaim) {
  std::vector<ValidationCase> cases = optics_cases();
  for (auto& c : geometry_cases()) cases.push_back(c);
  for (auto& c : physics_cases()) cases.push_back(c);
  std::string names;
  for (const ValidationCase& c : cases) {
    EXPECT_TRUE(c.pass()) << c.name << ": expected " << c.expected << ", obtained " << c.obtained
                          << ", tolerance " << c.tolerance;
    names += c.name + "\n";
  }
  for (const char* part :
       {"silver n=0.056+4.276i at 80 deg", "n=1.5+0.3i, mu=2 at 60 deg",
        "exponential beam (5.1), on the axis", "cut by its edge", "radii 1e-4 and 6e-5 m"})
    EXPECT_CONTAINS(names, part);
}

// The tolerances are what the rays earn (errors 3e-8 to 3e-5 relative), not the 1e-3 that let a
// wrong beam radius through: none above 1e-4 relative, the ones on the axis at 1e-6.
TEST(ValidateCases, SingleSphereTolerancesAreWhatTheRaysEarn) {
  int cases = 0;
  for (const ValidationCase& c : physics_cases()) {
    if (c.name.rfind("single sphere", 0) != 0) continue;
    ++cases;
    const bool on_axis = c.name.find("on the axis") != std::string::npos;
    EXPECT_LE(c.tolerance, (on_axis ? 1e-6 : 1e-4) * c.expected) << c.name;
  }
  EXPECT_EQ(cases, 3);
}

TEST(StabilityGrid, RefusesOnlyForTheReasonsItExpects) {
  const std::string diverges =
      "thermal fixed-point iteration (3.11) diverges at iteration 4 (relative update 3.1e-05, "
      "update ratio 12, contraction bound ...): use thermal.solver = \"cg\"";
  const std::string cg_cap =
      "thermal conjugate gradients did not reach thermal.tolerance = 1e-10 within "
      "thermal.max_iterations = 1000 (relative residual 2e-09): raise thermal.max_iterations";
  const std::string substeps =
      "`thermal.dt` = 1e-09 s: a step of 1e-09 s with thermal.phi = 0.5 exceeds the limit for a "
      "monotone step 4.3e-13 s (...) and would need 2333 sub-steps > thermal.max_substeps = 1000: "
      "use thermal.phi = 1";
  EXPECT_TRUE(expected_refusal("fixed-point", "1.0", diverges, true));
  EXPECT_TRUE(expected_refusal("cg", "1.0", cg_cap, true));
  EXPECT_TRUE(expected_refusal("direct", "0.5", substeps, false));
  // The same reasons from a solver or a phi that cannot give them, or as the other error type.
  EXPECT_FALSE(expected_refusal("cg", "1.0", diverges, true));
  EXPECT_FALSE(expected_refusal("direct", "1.0", cg_cap, true));
  EXPECT_FALSE(expected_refusal("direct", "1.0", substeps, false));
  EXPECT_FALSE(expected_refusal("fixed-point", "1.0", diverges, false));
  // Input the grid's own settings should never draw: a key renamed, a value rejected.
  EXPECT_FALSE(
      expected_refusal("auto", "1.0", "--set material.conductivty=100: unknown key", false));
  EXPECT_FALSE(expected_refusal("direct", "0.5", "`thermal.phi` = 0.5: must be in [0, 1]", false));
  EXPECT_FALSE(expected_refusal("cg", "1.0", "thermal conjugate gradients broke down", true));
}

TEST(StabilityGrid, SolversThatEndApartDisagree) {
  const FinalState direct{{300.0, 512.25, 650.0}, {Phase::solid, Phase::solid, Phase::liquid}, 0};
  FinalState close = direct;
  close.temperature[1] += 4e-9;  // the worst disagreement measured over the grid
  EXPECT_EQ(solver_disagreement(direct, close), "");
  FinalState early = direct;  // a solver that stopped early
  early.temperature[1] += 1e-3;
  EXPECT_CONTAINS(solver_disagreement(direct, early), "max |dtheta| = 0.001 K (limit 1e-06 K)");
  FinalState melted = direct;
  melted.phase[1] = Phase::liquid;
  EXPECT_CONTAINS(solver_disagreement(direct, melted), "1 particles in another phase");
  FinalState gone = direct;
  gone.vaporized_fraction = 0.01;
  EXPECT_CONTAINS(solver_disagreement(direct, gone), "vaporised fraction off by 0.01");
  FinalState nan = direct;
  nan.temperature[0] = std::nan("");
  EXPECT_CONTAINS(solver_disagreement(direct, nan), "max |dtheta| = nan");
}

}  // namespace
