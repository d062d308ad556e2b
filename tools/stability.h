#pragma once
#include <string>
#include <vector>

#include "geometry/particles.h"

namespace beampack::tools {

// The stability grid; prints a table and returns 0 unless a cell failed (refusals it expects are
// fine). `only` ("K=1e6", "dt=paper,1e-9", ...) keeps the cells whose column has one of the
// values, every entry at once; a column or value not in the grid is an InputError.
int run_stability_report(bool quiet, const std::vector<std::string>& only = {});

// Whether the grid expects a cell of this solver and thermal.phi to be refused with `message`
// (solver_refusal: a SolverRefusal, else an InputError): the fixed-point iteration diverging, CG
// at thermal.max_iterations, phi < 1 beyond thermal.max_substeps. Nothing else.
bool expected_refusal(const std::string& solver, const std::string& phi, const std::string& message,
                      bool solver_refusal);

// The end of a cell that ran, for comparing the solvers of a group.
struct FinalState {
  std::vector<double> temperature;
  std::vector<Phase> phase;
  double vaporized_fraction = 0;
};

// Empty when `other` ends where `reference` does (temperatures to 1e-6 K, the same phases, the
// same vaporised fraction); else what differs, with the numbers.
std::string solver_disagreement(const FinalState& reference, const FinalState& other);

}  // namespace beampack::tools
