#!/usr/bin/env bash
# Builds the test runner and the command with AddressSanitizer + UndefinedBehaviorSanitizer in
# ./build-asan and runs the whole test suite under them; any report fails the run.
#   scripts/sanitize.sh [extra cmake options]
# RelWithDebInfo (-O2 -g): the suite is dominated by tracing and solves; optimised, it runs in
# 20-33 s under the sanitizers (5 s without), so the whole suite runs, not a subset.
# Benchmarks are left out: they are not tests and take a third of the build.
# Compiler: clang when installed (CXX=... overrides): measured on 2 cores, clang builds this in
# 2.3-4.7 min (the machine is shared) against gcc's 9.5; both run the suite in 20-33 s with
# zero reports.
set -euo pipefail
cd "$(dirname "$0")/.."
if [[ -z "${CXX:-}" ]] && command -v clang++ >/dev/null; then export CC=clang CXX=clang++; fi
# CMake cannot switch the compiler of an existing build directory: start it afresh if it differs.
if [[ -f build-asan/CMakeCache.txt ]] &&
   ! grep -q "^CMAKE_CXX_COMPILER:[A-Z]*=$(command -v "${CXX:-c++}")$" build-asan/CMakeCache.txt; then
  rm -rf build-asan
fi
# BEAMPACK_CHECKS: the hot paths' invariants (geometry/check.h) are checked throughout the suite.
cmake -S . -B build-asan -G Ninja -DCMAKE_BUILD_TYPE=RelWithDebInfo -DBEAMPACK_SANITIZE=ON -DBEAMPACK_CHECKS=ON \
      -DBEAMPACK_BUILD_BENCHMARKS=OFF "$@" >/dev/null
cmake --build build-asan -j"$(nproc)" --target beampack-tests beampack_cli
# halt_on_error/abort_on_error: the first report ends the test with a failure, so ctest sees it.
# detect_leaks: leaks are reports too. strict_string_checks / check_initialization_order /
# detect_stack_use_after_return widen what ASan looks for beyond its defaults.
export ASAN_OPTIONS="halt_on_error=1:abort_on_error=1:detect_leaks=1:strict_string_checks=1:check_initialization_order=1:detect_stack_use_after_return=1${ASAN_OPTIONS:+:$ASAN_OPTIONS}"
# -fno-sanitize-recover=undefined already makes every UB report fatal; print where it happened.
export UBSAN_OPTIONS="halt_on_error=1:abort_on_error=1:print_stacktrace=1${UBSAN_OPTIONS:+:$UBSAN_OPTIONS}"
ctest --test-dir build-asan -j2 --output-on-failure
