#pragma once
// Errors a user can fix: bad input (exit code 2). Messages name the key, the value and the limit.
#include <sstream>
#include <stdexcept>
#include <string>

namespace beampack {

// A number as messages show it: 6 significant digits, with an exponent when it needs one ("1e-13",
// where std::to_string gives "0.000000").
inline std::string shown_number(double v) {
  std::ostringstream s;
  s << v;
  return s.str();
}

// An upper limit beyond which a run's arithmetic breaks, physically generous: messages give it as
// "must be <= limit why", `why` its unit and reason.
struct Cap {
  double limit;
  const char* why;
};

// "must be <= 1e+20 W/(m K) (...)": the limit as messages state it.
inline std::string cap_limit(const Cap& cap) {
  return "must be <= " + shown_number(cap.limit) + " " + cap.why;
}

class InputError : public std::runtime_error {
 public:
  using std::runtime_error::runtime_error;
};

// A run that started from valid input and could not finish (exit code 1): a solver that does not
// converge, a NaN detected mid-run, ...
class RunError : public std::runtime_error {
 public:
  using std::runtime_error::runtime_error;
};

// A solver declining a step beyond its limits, with advice: the fixed-point iteration past its
// contraction limit, CG past its iteration cap. A refusal, not a defect: every other RunError (a
// NaN, energy into a vaporised particle) is one, and the stability grid fails on it.
class SolverRefusal : public RunError {
 public:
  using RunError::RunError;
};

}  // namespace beampack
