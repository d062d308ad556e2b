#pragma once
// `beampack validate`: analytic cases with expected, obtained, tolerance and pass/fail.
#include <functional>
#include <string>
#include <vector>

namespace beampack::tools {

struct ValidationCase {
  std::string name;
  double expected;
  double obtained;
  double tolerance;  // absolute
  bool pass() const;
};

std::vector<ValidationCase> optics_cases();
std::vector<ValidationCase> geometry_cases();
std::vector<ValidationCase> physics_cases();

// Prints the table to stdout; returns the exit code (0 only if all pass).
int run_validate(bool quiet);

}  // namespace beampack::tools
