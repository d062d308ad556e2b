#pragma once
// What the fuzz targets check, shared with the GoogleTest runner that replays every corpus and
// regression file (tests/test_fuzz_regressions.cpp), so default CI checks them without clang.
//
// Acceptable outcomes for any bytes: the input is accepted and everything resolved from it is
// sane, or it is refused with an InputError. Anything else (another exception, a NaN or infinity
// in the resolved values, a particle that is not a finite sphere) is a bug; a crash or a
// sanitizer report is caught by the fuzzer itself.
#include <cstdint>
#include <span>
#include <string>

namespace beampack::fuzz {

struct Outcome {
  bool accepted = false;    // parsed without error
  std::string input_error;  // InputError message when refused (a fine outcome)
  std::string bug;          // non-empty: what is wrong (the target aborts on it)
};

// The bytes as a run file through tools::load_run_config (via a temporary file). Bytes after the
// first NUL, if any, are extra command-line layers, one per line: `--preset NAME` or KEY=VALUE
// (as `--set`), so the fuzzer also reaches presets and overrides.
Outcome check_run_file(std::span<const std::uint8_t> bytes);

// The bytes as a packing file through read_packing_file, once as `x y z r` and once as `x y z`
// with a given radius. Accepted: every particle has a finite centre, a finite radius > 0, and a
// finite, positive volume and bounding box.
Outcome check_packing_file(std::span<const std::uint8_t> bytes);

// A target's verdict on one input: a bug is printed with the target's name and aborts the
// process (libFuzzer saves the input as a crash artifact); anything else returns 0.
int report(const Outcome& outcome, const char* target);

}  // namespace beampack::fuzz
