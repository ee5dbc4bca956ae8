#!/usr/bin/env bash
# GPU run for object deletion (one H100): build with CUDA, then benchmarks/delete.py on the demo
# tabletop at density 16 (~316k Gaussians) with 40 views of 640x480 around the mug, OpenCV
# inpainting, 300 refit steps; once as is and once with the table under the mug carved out (a
# real hole that seeds and the refit fill). Results: $OUT/delete.txt, $OUT/delete_*.json.
# Usage (device call, after copying this tree to .carry/delete):
#   cd .carry/delete && OUT=$OUT bash benchmarks/gpu/delete.sh
set -uo pipefail
cd "$(dirname "$0")/../.."
OUT="${OUT:-/tmp/tiger-gpu}"
mkdir -p "$OUT"
DEB="$(ls ../deb/*.deb .carry/deb/*.deb 2>/dev/null | head -1)"
CHECK_STEPS=build bash benchmarks/gpu/check.sh "" "$DEB" || { echo "build failed"; exit 1; }
PY="${PYTHON:-python3}"
{
  for carve in "" "--carve"; do
    echo "== delete ${carve:-(table intact)}: $(date -u +%T)"
    "$PY" -m benchmarks.delete --device cuda --density 16 --views 40 --size 640x480 --steps 300 \
      --repeats 2 $carve --json "$OUT/delete${carve:+_carved}.json" 2>&1 | grep -v Warning
  done
} | tee "$OUT/delete.txt"
