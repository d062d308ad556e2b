// libFuzzer target: arbitrary bytes as a packing file (x y z r, or x y z with a radius).
#include "fuzz/fuzz_checks.h"

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
  return beampack::fuzz::report(beampack::fuzz::check_packing_file({data, size}), "packing file");
}
