#!/usr/bin/env bash
# One device call for tiger::jittered_window_attention's CUDA kernel variants (csrc/featup/featup.h):
# the CUDA tests of tests/language/test_featup_fused.py (every variant against the CPU kernels, the
# float64 reference at the fit's geometry and the baseline at the full one), compute-sanitizer
# memcheck and racecheck on a small workload of every variant (benchmarks/gpu/sanitize_window_attention.py),
# then benchmarks/featup_ops.py --only attention (every variant side by side at the fit's geometry)
# and the implicit fit (bf16, no reference fit) per variant (ImplicitConfig.attention_variant, by
# featup_implicit's --variants; the default list alternates baseline and pixel_dots for an A/B).
# From the repo root after `make build`; logs under $OUT/attention_variants.
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
if [ "${FIT:-1}" = 1 ]; then  # FIT=0 skips the fits (about 10 s a variant and seed)
  specs=""
  for variant in ${FIT_VARIANTS:-baseline pixel_dots baseline pixel_dots}; do specs="$specs attention_variant=$variant"; done
  timeout 600 "$PY" -m benchmarks.featup_implicit --device cuda --no-reference --no-fp32 --variants $specs \
    > "$LOG/fits.txt" 2>&1
  echo "== implicit fits per attention variant (rc=$?)"; grep -A14 "^implicit FeatUp fit, per image" "$LOG/fits.txt"
fi
