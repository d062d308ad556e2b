// libFuzzer target: arbitrary bytes as a packing file (x y z r, or x y z with a radius).
#include <cstdio>
#include <cstdlib>

#include "fuzz/fuzz_checks.h"

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
  const beampack::fuzz::Outcome o = beampack::fuzz::check_packing_file({data, size});
  if (!o.bug.empty()) {
    std::fprintf(stderr, "beampack fuzz bug (packing file): %s\n", o.bug.c_str());
    std::abort();  // libFuzzer saves the input as a crash artifact
  }
  return 0;
}
