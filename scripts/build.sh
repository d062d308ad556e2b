#!/usr/bin/env bash
# Configures and builds beampack in ./build (Release-with-debug-info, -O2, portable ISA).
set -euo pipefail
cd "$(dirname "$0")/.."
cmake -S . -B build -G Ninja -DCMAKE_BUILD_TYPE=RelWithDebInfo "$@" >/dev/null
cmake --build build -j"$(nproc)"
