#pragma once
namespace beampack::tools {
// The stability grid; prints a table and returns 0 unless a cell failed (refusals are fine).
int run_stability_report(bool quiet);
}  // namespace beampack::tools
