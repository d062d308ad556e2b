#include "tools/validate.h"

#include <cmath>
#include <cstdio>

namespace beampack::tools {

bool ValidationCase::pass() const {
  return std::isfinite(obtained) && std::abs(obtained - expected) <= tolerance;
}

int run_validate(bool quiet) {
  std::vector<ValidationCase> cases = optics_cases();
  for (auto& c : geometry_cases()) cases.push_back(std::move(c));
  for (auto& c : physics_cases()) cases.push_back(std::move(c));
  int failed = 0;
  if (!quiet)
    std::printf("%-58s %14s %14s %9s  %s\n", "case", "expected", "obtained", "tolerance", "result");
  for (const ValidationCase& c : cases) {
    failed += !c.pass();
    if (!quiet || !c.pass())
      std::printf("%-58s %14.8g %14.8g %9.1e  %s\n", c.name.c_str(), c.expected, c.obtained,
                  c.tolerance, c.pass() ? "pass" : "FAIL");
  }
  std::printf("validate: %zu passed, %d failed\n", cases.size() - failed, failed);
  return failed == 0 ? 0 : 1;
}

}  // namespace beampack::tools
