// The hot paths' invariant checks (geometry/check.h): in a BEAMPACK_CHECKS build
// (scripts/sanitize.sh runs the whole suite in one) a broken invariant stops the process with what
// broke and how to reproduce it; elsewhere a check is not even evaluated.
#include <gtest/gtest.h>

#include "geometry/check.h"

namespace {

int evaluations = 0;
[[maybe_unused]] bool counted(bool value) {
  ++evaluations;
  return value;
}

}  // namespace

TEST(Checks, AFailedCheckNamesTheConditionTheFactsAndTheStep) {
  if (!BEAMPACK_CHECKS_ON)
    GTEST_SKIP() << "checks are compiled out of this build (-DBEAMPACK_CHECKS=ON)";
  GTEST_FLAG_SET(death_test_style, "threadsafe");
  EXPECT_DEATH(
      {
        beampack::set_check_context("step 7 (t = 1e-12 s)");
        const double reflectance = 1.5;
        BEAMPACK_DCHECK(reflectance <= 1.0, "ray %d: reflectance %g", 3, reflectance);
      },
      "internal check failed at .*test_checks.cpp:[0-9]+: reflectance <= 1.0\n  ray 3: reflectance "
      "1.5\n"
      "  to reproduce: step 7 \\(t = 1e-12 s\\)");
  BEAMPACK_DCHECK(counted(true), "holds");
  EXPECT_EQ(evaluations, 1);
}

TEST(Checks, ACheckOutsideAChecksBuildIsNotEvaluated) {
  if (BEAMPACK_CHECKS_ON) GTEST_SKIP() << "a BEAMPACK_CHECKS build evaluates its checks";
  BEAMPACK_DCHECK(counted(false), "never evaluated");
  EXPECT_EQ(evaluations, 0);
}
