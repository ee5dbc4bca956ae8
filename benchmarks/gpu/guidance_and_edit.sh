#!/usr/bin/env bash
# One device call for the diffusion guidance and the edit loop on one GPU: tiger::group_norm (CUDA tests, op benchmark,
# compute-sanitizer; benchmarks/gpu/group_norm.sh), then the guidance step with fused norms and a
# 1200-step CSD edit (benchmarks/gpu/fused_vae.sh), then the CUDA tests of tests/edit. The device
# returns few files: everything is packed into $OUT/results.tgz, the summary goes to stdout.
# From the repo root with .whl and .carry/deb carried.
cd "$(dirname "$0")/../.."
export OUT="${OUT:-outputs}" PYTHONUNBUFFERED=1 TOKENIZERS_PARALLELISM=false
mkdir -p "$OUT/gn" "$OUT/run"
BENCH_ARGS="${GN_BENCH_ARGS:---skip-models}" OUT="$OUT/gn" bash benchmarks/gpu/group_norm.sh .whl \
  .carry/deb/libeigen3-dev_3.4.0-4_all.deb > /dev/null 2>&1
grep -v "^\[.*\] \(GPU\|python\|nvcc\|wheels\)" "$OUT/gn/check.log" | tail -8
OUT="$OUT/run" FUSED="${FUSED:-all}" bash benchmarks/gpu/fused_vae.sh 2>&1 | tail -8
export PYTHONPATH="/tmp/site${PYTHONPATH:+:$PYTHONPATH}"
timeout "${TESTS_TIMEOUT:-120}" python3 -m pytest -q -p no:cacheprovider tests/edit > "$OUT/run/edit_tests.log" 2>&1
echo "tests/edit on CUDA: $(tail -1 "$OUT/run/edit_tests.log")"
(cd "$OUT" && tar czf results.tgz gn run && rm -rf gn run)
