#!/usr/bin/env bash
# Builds the libFuzzer targets with clang (address + undefined-behaviour sanitizers) in
# ./build-fuzz and runs each for a bounded time over its seed corpus and regression files.
#   scripts/fuzz.sh [seconds per target, default 30]
# A finding fails the run and leaves the input in build-fuzz/fuzz-artifacts/<target>/; once
# fixed, copy it to fuzz/regressions/<target>/ so every test run replays it.
set -euo pipefail
cd "$(dirname "$0")/.."
seconds="${1:-30}"
CC=clang CXX=clang++ cmake -S . -B build-fuzz -G Ninja -DCMAKE_BUILD_TYPE=RelWithDebInfo \
      -DBEAMPACK_FUZZ=ON -DBEAMPACK_FUZZ_SECONDS="$seconds" -DBEAMPACK_BUILD_TESTS=OFF \
      -DBEAMPACK_BUILD_BENCHMARKS=OFF >/dev/null
cmake --build build-fuzz -j"$(nproc)" --target fuzz_run_config fuzz_packing_file
export ASAN_OPTIONS="halt_on_error=1:abort_on_error=1:detect_leaks=1${ASAN_OPTIONS:+:$ASAN_OPTIONS}"
export UBSAN_OPTIONS="halt_on_error=1:abort_on_error=1:print_stacktrace=1${UBSAN_OPTIONS:+:$UBSAN_OPTIONS}"
# The two targets run side by side (one core each).
ctest --test-dir build-fuzz -L fuzz -j2 --output-on-failure
