#!/usr/bin/env bash
# GPU run of tiger::group_norm and the fused-norm models, in one call on one GPU: build with CUDA
# (check.sh's build step), the CUDA tests of the op, the fused models and the CUDA-graph guidance
# test, the benchmark, then compute-sanitizer memcheck and racecheck on a small workload.
# From the repo root on the device:  OUT=... bash benchmarks/gpu/group_norm.sh WHEEL_DIR EIGEN_DEB
# Results under $OUT: check.log, build.log, tests.log, group_norm_h100.{txt,json}, sanitizer.log.
set -uo pipefail
cd "$(dirname "$0")/../.."
OUT="${OUT:-/tmp/tiger-group-norm}"
mkdir -p "$OUT"
PY="${PYTHON:-python3}"
export PYTHONUNBUFFERED=1 TOKENIZERS_PARALLELISM=false
CHECK_STEPS=build bash benchmarks/gpu/check.sh "$1" "$2" || { echo "build failed"; exit 1; }
export PYTHONPATH="/tmp/site${PYTHONPATH:+:$PYTHONPATH}"  # check.sh installed the wheels there
say() { echo "[$(date -u +%H:%M:%S)] $*" | tee -a "$OUT/check.log"; }
say "tests"
timeout "${TESTS_TIMEOUT:-100}" $PY -m pytest -q -p no:cacheprovider -rs tests/ops/test_group_norm.py \
  tests/ops/test_channel_bias.py tests/edit/test_fused_norms.py tests/edit/test_cuda_graph.py > "$OUT/tests.log" 2>&1
say "tests rc=$?: $(tail -1 "$OUT/tests.log")"
grep -E "^(FAILED|ERROR)" "$OUT/tests.log" | head -20 | tee -a "$OUT/check.log"
say "benchmark"
timeout "${BENCH_TIMEOUT:-140}" $PY -m benchmarks.group_norm --device cuda ${BENCH_ARGS:-} --json "$OUT/group_norm_h100.json" \
  > "$OUT/group_norm_h100.txt" 2>&1
say "benchmark rc=$?"
SAN="$(command -v compute-sanitizer || echo /usr/local/cuda/bin/compute-sanitizer)"
PYTORCH_NO_CUDA_MEMORY_CACHING=1 timeout "${SANITIZER_TIMEOUT:-45}" "$SAN" --tool memcheck --error-exitcode 99 \
  $PY -m benchmarks.gpu.sanitize_group_norm > "$OUT/sanitizer.log" 2>&1
say "memcheck rc=$?: $(grep -E 'ERROR SUMMARY' "$OUT/sanitizer.log" | tail -1)"
timeout "${SANITIZER_TIMEOUT:-45}" "$SAN" --tool racecheck --error-exitcode 99 --kernel-name kns=group_norm \
  $PY -m benchmarks.gpu.sanitize_group_norm >> "$OUT/sanitizer.log" 2>&1
say "racecheck rc=$?: $(grep -E 'RACECHECK SUMMARY|ERROR SUMMARY' "$OUT/sanitizer.log" | tail -1)"
say "done"
