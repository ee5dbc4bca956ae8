#!/usr/bin/env bash
# Eigen3 for the C++ build: use what CMake finds; install Debian's package if root.
set -euo pipefail
for d in /usr/include/eigen3 /usr/local/include/eigen3 "${CONDA_PREFIX:-/nonexistent}/include/eigen3"; do
  if [ -f "$d/Eigen/Core" ]; then exit 0; fi
done
if [ "$(id -u)" = "0" ] && command -v apt-get >/dev/null; then
  echo "Eigen3 not found: installing Debian's libeigen3-dev"
  apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq libeigen3-dev >/dev/null
  exit 0
fi
echo "error: Eigen3 headers not found. Install them (Debian/Ubuntu: sudo apt-get install libeigen3-dev;" >&2
echo "       conda: conda install -c conda-forge eigen) and run make again." >&2
exit 1
