#!/usr/bin/env bash
# Installs what beampack needs from Debian packages. Safe to run twice.
set -euo pipefail
packages=(build-essential cmake ninja-build pkg-config
          libembree-dev libeigen3-dev libtbb-dev libgtest-dev libbenchmark-dev
          libcli11-dev libtomlplusplus-dev nlohmann-json3-dev python3-vtk9
          clang libclang-rt-14-dev clang-format)
missing=()
for p in "${packages[@]}"; do
  dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q "install ok installed" || missing+=("$p")
done
if ((${#missing[@]})); then
  sudo=""; [ "$(id -u)" -eq 0 ] || sudo="sudo"
  echo "setup: installing ${missing[*]}" >&2
  $sudo apt-get update -qq
  DEBIAN_FRONTEND=noninteractive $sudo apt-get install -y -qq --no-install-recommends "${missing[@]}" >/dev/null
else
  echo "setup: all packages present" >&2
fi
