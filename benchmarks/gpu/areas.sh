#!/usr/bin/env bash
# One device call for several areas: build with CUDA (check.sh's build step, incremental on a
# warm machine), then run each named area script (features, retrieval, scene, check) with its
# results under $OUT. Usage: OUT=... bash benchmarks/gpu/areas.sh features retrieval scene
set -uo pipefail
cd "$(dirname "$0")/../.."
OUT="${OUT:-/tmp/tiger-gpu}"
mkdir -p "$OUT"
DEB="$(ls .carry/deb/*.deb 2>/dev/null | head -1)"
CHECK_STEPS=build bash benchmarks/gpu/check.sh "" "$DEB" || { echo "build failed"; exit 1; }
export CXX=/usr/bin/g++ CC=/usr/bin/gcc PYTHON=python3
for area in "$@"; do
  echo "== area $area: $(date -u +%T)"
  case "$area" in
    check) CHECK_STEPS="${AREA_CHECK_STEPS:-tests sanitizer}" bash benchmarks/gpu/check.sh ;;
    *) bash "benchmarks/gpu/$area.sh" ;;
  esac
  echo "== area $area done: $(date -u +%T)"
done
