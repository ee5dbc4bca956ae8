#!/usr/bin/env bash
# GPU run of the diffusion guidances: full-size random-weight InstructPix2Pix and MVDream,
# every variant of benchmarks/guidance.py in one call. Run from the repo root on the device with
# the diffusers wheel and Eigen's .deb carried (first the CUDA-graph test, then the benchmark):
#   WHEELS=../../.whl EIGEN_DEB=../deb/libeigen3-dev_3.4.0-4_all.deb bash benchmarks/gpu/guidance.sh
# Results: $OUT/guidance_h100.{json,txt}, $OUT/profile_*.txt, $OUT/{build,check}.log.
set -uo pipefail
OUT="${OUT:-outputs}"
mkdir -p "$OUT"
PY="${PYTHON:-python3}"
export PYTHONUNBUFFERED=1 TOKENIZERS_PARALLELISM=false
t0=$(date +%s)
if [ -n "${WHEELS:-}" ]; then
  $PY -m pip install -q --no-index --no-deps --no-compile --target /tmp/site "$WHEELS"/diffusers-*.whl || exit 1
  export PYTHONPATH="/tmp/site${PYTHONPATH:+:$PYTHONPATH}"
fi
# check.sh's build step (tiger with CUDA; the same build serves edit.sh and the tests)
OUT="$OUT" CHECK_STEPS=build bash benchmarks/gpu/check.sh "" "${EIGEN_DEB:-}" || { echo "BUILD FAILED"; exit 1; }
echo "setup done in $(( $(date +%s) - t0 )) s"
nvidia-smi --query-gpu=name,memory.total --format=csv,noheader
echo "== CUDA-graph replay vs eager (tiny models)"
timeout 150 $PY -m pytest -q tests/edit/test_cuda_graph.py -p no:cacheprovider 2>&1 | tail -5
echo "== benchmark"
$PY -m benchmarks.guidance --device cuda --out "$OUT/guidance_h100.json" --profile-dir "$OUT" \
    --budget-s "${BUDGET_S:-220}" ${GUIDANCE_ARGS:-} 2>&1 | grep -v -i -e "warn" -e "Model config" | tee "$OUT/guidance_h100.txt"
