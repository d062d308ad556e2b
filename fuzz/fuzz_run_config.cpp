// libFuzzer target: arbitrary bytes as a TOML run file (plus --preset/--set layers after a NUL).
#include "fuzz/fuzz_checks.h"

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
  return beampack::fuzz::report(beampack::fuzz::check_run_file({data, size}), "run file");
}
