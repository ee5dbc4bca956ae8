#!/usr/bin/env bash
# One device call for tiger::jittered_window_attention's CUDA kernel variants (csrc/featup/featup.h):
# the CUDA tests of tests/language/test_featup_fused.py (every variant against the CPU kernels, the
# float64 reference at the fit's geometry and the baseline at the full one), compute-sanitizer
# memcheck and racecheck on a small workload of every variant (benchmarks/gpu/sanitize_window_attention.py),
# then benchmarks/featup_ops.py --only attention (every variant side by side at the fit's geometry)
# and the implicit fit (bf16, no reference fit) per variant (the op's default swapped in by a wrapper: the fit itself has no
# setting for it). From the repo root after `make build`; logs under $OUT/attention_variants.
cd "$(dirname "$0")/../.."
export OUT="${OUT:-outputs}" PYTHONUNBUFFERED=1
PY="${PY:-python3}"
LOG="$OUT/attention_variants"
mkdir -p "$LOG"
timeout 900 "$PY" -m pytest -q -p no:cacheprovider tests/language/test_featup_fused.py > "$LOG/tests.log" 2>&1
echo "tests rc=$?: $(tail -1 "$LOG/tests.log")"
SAN="$(command -v compute-sanitizer || echo /usr/local/cuda/bin/compute-sanitizer)"
for tool in memcheck racecheck; do
  PYTORCH_NO_CUDA_MEMORY_CACHING=1 timeout 600 "$SAN" --tool $tool --target-processes all --error-exitcode 99 \
    "$PY" -m benchmarks.gpu.sanitize_window_attention > "$LOG/$tool.log" 2>&1
  echo "$tool rc=$?: $(grep -E 'ERROR SUMMARY|RACECHECK SUMMARY' "$LOG/$tool.log" | tail -1)"
done
timeout 600 "$PY" -m benchmarks.featup_ops --device cuda --only attention > "$LOG/featup_ops.txt" 2>&1
tail -9 "$LOG/featup_ops.txt"
if [ "${FIT:-1}" = 1 ]; then  # FIT=0 skips the fits (about 1 min each)
  for variant in ${FIT_VARIANTS:-baseline staged_tiles staged_tiles_bf16}; do
    timeout 600 "$PY" - "$variant" > "$LOG/fit_$variant.txt" 2>&1 <<'EOF'
import functools, runpy, sys
import tiger.ops.featup as ops
variant = sys.argv[1]
ops.jittered_window_attention = functools.partial(ops.jittered_window_attention, variant=variant)
sys.argv = ["benchmarks.featup_implicit", "--device", "cuda", "--no-reference", "--no-fp32"]
runpy.run_module("benchmarks.featup_implicit", run_name="__main__")
EOF
    echo "== implicit fit, attention variant $variant (rc=$?)"; tail -12 "$LOG/fit_$variant.txt"
  done
fi
