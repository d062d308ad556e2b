#pragma once
#include <optional>

#include "tools/run_command.h"

namespace beampack::tools {
// A rung's final temperatures against the reference's, over the particles live at the end of
// both: a vaporised particle's temperature is the one it left with, not a field value (a
// difference in what vaporised is the vaporised fraction's error). Empty, not 0 K, where no
// particle is live in both runs: nothing was compared.
struct TemperatureError {
  std::optional<double> l2;   // root mean square difference, K
  std::optional<double> max;  // largest difference, K
  std::size_t compared = 0;   // particles live in both runs
};
TemperatureError temperature_error(const RunResult& rung, const RunResult& reference);

// Writes convergence.csv and convergence.svg in options.out_dir; returns the exit code.
int converge_command(const RunOptions& options);
}  // namespace beampack::tools
