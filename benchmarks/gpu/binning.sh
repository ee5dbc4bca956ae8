#!/usr/bin/env bash
# One device call for the load-balanced binning and the real-scene benchmarks:
#   build (check.sh), the test suite, compute-sanitizer (memcheck on every kernel, racecheck on
#   the binning kernels), benchmarks/gpu/real_scenes.py (ours, ours
#   with the former binning, gsplat: per stage, C = 3 and 64) and train_vs_gsplat.py.
# Usage, from the repo root:
#   OUT=... bash benchmarks/gpu/binning.sh GSPLAT_WHEEL_DIR EIGEN_DEB DATA_DIR [STEPS]
# DATA_DIR holds snowmiku/ (points3D.bin, cameras.bin, cameras.json) and fox/ (transforms.json,
# images/). STEPS (default "check real train") picks the parts; REAL_ARGS, TRAIN_ARGS,
# CHECK_STEPS pass options on.
set -uo pipefail
cd "$(dirname "$0")/../.."
OUT="${OUT:-/tmp/tiger-binning}"
mkdir -p "$OUT"
WHEELS="$1"; DEB="$2"; DATA="$3"; STEPS="${4:-check real train}"
has() { [[ " $STEPS " == *" $1 "* ]]; }
export PYTHONUNBUFFERED=1 MAX_JOBS=$(nproc) TORCH_CUDA_ARCH_LIST=9.0
status=0
if has check; then CHECK_STEPS="${CHECK_STEPS:-build tests sanitizer}"; else CHECK_STEPS=build; fi
CHECK_STEPS="$CHECK_STEPS" bash benchmarks/gpu/check.sh "$WHEELS" "$DEB" || status=1
[ $status -eq 0 ] && rm -f "$OUT/build.log"  # at most 8 files come back
export PYTHONPATH="/tmp/site${PYTHONPATH:+:$PYTHONPATH}"
if has sanitize; then  # the binning kernels changed: memcheck on every kernel, racecheck on them
  SAN="$(command -v compute-sanitizer || echo /usr/local/cuda/bin/compute-sanitizer)"
  PYTORCH_NO_CUDA_MEMORY_CACHING=1 timeout 200 "$SAN" --tool memcheck --error-exitcode 99 \
    python3 -m benchmarks.gpu.sanitize_case > "$OUT/memcheck.log" 2>&1
  rc=$?; [ $rc -ne 0 ] && status=1
  echo "[$(date -u +%T)] memcheck (every kernel) rc=$rc: $(grep -E 'ERROR SUMMARY' "$OUT/memcheck.log" | tail -1)" | tee -a "$OUT/check.log"
  timeout 200 "$SAN" --tool racecheck --error-exitcode 99 --kernel-name kns=bin_cuda \
    python3 -m benchmarks.gpu.sanitize_case > "$OUT/racecheck_binning.log" 2>&1
  rc=$?; [ $rc -ne 0 ] && status=1
  echo "[$(date -u +%T)] racecheck (binning kernels) rc=$rc: $(grep -E 'RACECHECK SUMMARY|ERROR SUMMARY' "$OUT/racecheck_binning.log" | tail -1)" | tee -a "$OUT/check.log"
fi
if has cudatests; then
  python3 -m pytest -q -p no:cacheprovider ${CUDATESTS:-tests/render/test_binning.py tests/render/test_cuda.py} \
    > "$OUT/cudatests.log" 2>&1
  rc=$?; [ $rc -ne 0 ] && status=1
  echo "[$(date -u +%T)] render + binning tests (CPU and CUDA) rc=$rc: $(tail -1 "$OUT/cudatests.log")" | tee -a "$OUT/check.log"
  grep -E "^(FAILED|ERROR)" "$OUT/cudatests.log" | head -20
fi
if has train; then
  echo "== train_vs_gsplat.py $(date -u +%T)"
  timeout "${TRAIN_TIMEOUT:-300}" python3 -m benchmarks.gpu.train_vs_gsplat --data "$DATA/fox" \
    --json "$OUT/train_vs_gsplat.json" ${TRAIN_ARGS:-} > "$OUT/train_vs_gsplat.txt" 2>&1
  rc=$?; [ $rc -ne 0 ] && status=1
  echo "train rc=$rc"; tail -12 "$OUT/train_vs_gsplat.txt"
fi
if has real; then
  echo "== real_scenes.py $(date -u +%T)"
  timeout "${REAL_TIMEOUT:-420}" python3 -m benchmarks.gpu.real_scenes --snowmiku "$DATA/snowmiku" \
    --fox-data "$DATA/fox" --out "$OUT" ${REAL_ARGS:-} > "$OUT/real_scenes.txt" 2>&1
  rc=$?; [ $rc -ne 0 ] && status=1
  echo "real_scenes rc=$rc"; sed -n '/^== Screen radii/,$p' "$OUT/real_scenes.txt"
  [ $rc -ne 0 ] && tail -30 "$OUT/real_scenes.txt"
fi
# At most 8 files come back: the secondary logs travel as one archive.
(cd "$OUT" && ls *.log | grep -v '^check.log$' | tar czf logs.tgz -T - && ls *.log | grep -v '^check.log$' | xargs rm -f)
echo "== done status=$status $(date -u +%T)"
exit $status
