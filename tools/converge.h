#pragma once
#include "tools/run_command.h"

namespace beampack::tools {
// Writes convergence.csv and convergence.svg in options.out_dir; returns the exit code.
int converge_command(const RunOptions& options);
}  // namespace beampack::tools
