#!/usr/bin/env bash
# GPU run of the edit loop: build tiger with CUDA, then benchmarks/edit.py on a 317,600-Gaussian
# scene: recolor / analytic (the loop without diffusion) and a 1200-step CSD edit with full-size random
# InstructPix2Pix + MVDream (bf16, CUDA graphs, a pool of VIEW_POOL=64 camera sets). From the repo root on the device:
#   WHEELS=../../.whl EIGEN_DEB=../deb/libeigen3-dev_3.4.0-4_all.deb OUT=$OUT bash benchmarks/gpu/edit.sh
# Results: $OUT/edit_h100.json, $OUT/edit_h100.txt, $OUT/build.log.
set -uo pipefail
cd "$(dirname "$0")/../.."
export OUT="${OUT:-outputs}"
mkdir -p "$OUT"
PY="${PYTHON:-python3}"
export PYTHONUNBUFFERED=1 TOKENIZERS_PARALLELISM=false
t0=$(date +%s)
# check.sh's build step: the carried wheels (diffusers) go to /tmp/site, tiger is built with CUDA.
CHECK_STEPS=build bash benchmarks/gpu/check.sh "${WHEELS:-}" "${EIGEN_DEB:-}" || { echo "BUILD FAILED"; exit 1; }
export PYTHONPATH="/tmp/site${PYTHONPATH:+:$PYTHONPATH}"
echo "setup done in $(( $(date +%s) - t0 )) s; cuda_enabled=$($PY -c 'import tiger.ops as o; print(o.cuda_enabled())')"
nvidia-smi --query-gpu=name,memory.total --format=csv,noheader
$PY -m benchmarks.edit --device cuda --density 16 --guidance recolor analytic --steps 200 --size 512 \
    --json "$OUT/edit_h100_nodiffusion.json" 2>&1 | tee "$OUT/edit_h100_nodiffusion.txt"
for graph in --cuda-graph ""; do
  if $PY -m benchmarks.edit --device cuda --density 16 --guidance ip2p+mvdream --random-models full --dtype bf16 \
      --steps 1200 --size 512 --warmup 5 $graph --view-pool "${VIEW_POOL:-64}" --time-budget-s "${BUDGET_S:-150}" \
      --json "$OUT/edit_h100.json" \
      2>&1 | grep -v -i -e "warn" -e "Model config" | tee "$OUT/edit_h100${graph:+_graph}.txt"; then
    [ -f "$OUT/edit_h100.json" ] && break
  fi
  echo "run with '${graph}' failed; trying without CUDA graphs"
done
echo "total $(( $(date +%s) - t0 )) s"
