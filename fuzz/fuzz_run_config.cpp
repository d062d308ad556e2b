// libFuzzer target: arbitrary bytes as a TOML run file (plus --preset/--set layers after a NUL).
#include <cstdio>
#include <cstdlib>

#include "fuzz/fuzz_checks.h"

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
  const beampack::fuzz::Outcome o = beampack::fuzz::check_run_file({data, size});
  if (!o.bug.empty()) {
    std::fprintf(stderr, "beampack fuzz bug (run file): %s\n", o.bug.c_str());
    std::abort();  // libFuzzer saves the input as a crash artifact
  }
  return 0;
}
