#!/usr/bin/env bash
# One device call for the staged SH kernels (the default; sh_to_color's _staged=False selects the
# plain ones, which took 1.17 ms for the SH backward of the fox training step): build, the CUDA tests
# of tests/ops/test_sh.py (staged == plain bit for bit, and the float64 reference), compute-sanitizer
# memcheck/racecheck on the staged kernels, then benchmarks/sh.py plain vs staged beside gsplat and
# the training step with the staged kernels. Everything lands in $OUT/sh.tgz (the device returns few files).
# From the repo root with .whl, .carry/deb and .carry/realscene carried.
cd "$(dirname "$0")/../.."
export OUT="${OUT:-outputs}" PYTHONUNBUFFERED=1
mkdir -p "$OUT/sh"
CHECK_STEPS=build OUT="$OUT/sh" bash benchmarks/gpu/check.sh .whl .carry/deb/libeigen3-dev_3.4.0-4_all.deb >/dev/null 2>&1
tail -1 "$OUT/sh/check.log"
export PYTHONPATH="/tmp/site${PYTHONPATH:+:$PYTHONPATH}"
timeout 120 python3 -m pytest -q -p no:cacheprovider tests/ops/test_sh.py > "$OUT/sh/tests.log" 2>&1
echo "tests: $(tail -1 "$OUT/sh/tests.log")"
SAN="$(command -v compute-sanitizer || echo /usr/local/cuda/bin/compute-sanitizer)"
for tool in memcheck racecheck; do
  # the staged test runs both kernels (staged and plain) in the same process
  PYTORCH_NO_CUDA_MEMORY_CACHING=1 timeout 90 "$SAN" --tool $tool --target-processes all --error-exitcode 99 \
    --kernel-name kns=sh_ python3 -m pytest -q -p no:cacheprovider tests/ops/test_sh.py -k staged \
    > "$OUT/sh/$tool.log" 2>&1
  echo "$tool rc=$?: $(grep -E 'ERROR SUMMARY|RACECHECK SUMMARY' "$OUT/sh/$tool.log" | tail -1)"
done
for kernels in plain staged; do
  timeout 120 python3 -m benchmarks.sh --device cuda --n 1e5 1e6 4e6 $([ $kernels = plain ] && echo --plain) \
    > "$OUT/sh/bench_$kernels.txt" 2>&1
  echo "== sh.py, $kernels kernels"; tail -6 "$OUT/sh/bench_$kernels.txt"
done
if [ "${TRAIN:-1}" = 1 ]; then  # TRAIN=0 skips it (gsplat's JIT build alone takes 1-2 min)
  timeout 240 python3 -m benchmarks.gpu.train_vs_gsplat --data .carry/realscene/fox \
    > "$OUT/sh/train_vs_gsplat_staged.txt" 2>&1
  tail -8 "$OUT/sh/train_vs_gsplat_staged.txt"
fi
(cd "$OUT" && tar czf sh.tgz sh && rm -rf sh)
