#!/usr/bin/env bash
# GPU run of the edit loop (issue 13): build tiger with CUDA, then benchmarks/edit.py on a ~300k-Gaussian
# scene: recolor / analytic (the loop without diffusion) and a 1200-step CSD edit with full-size random
# InstructPix2Pix + MVDream (bf16, CUDA graphs). From the repo root on the device:
#   WHEELS=../../.whl EIGEN_DEB=../deb/libeigen3-dev_3.4.0-4_all.deb OUT=$OUT bash benchmarks/gpu/edit.sh
# Results: $OUT/edit_h100.json, $OUT/edit_h100.txt, $OUT/build.log.
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
EXTRA=()
if ! [ -f /usr/include/eigen3/Eigen/Core ] && [ -n "${EIGEN_DEB:-}" ]; then
  dpkg -x "$EIGEN_DEB" /tmp/eigen
  EXTRA+=(--config-settings=cmake.define.Eigen3_DIR=/tmp/eigen/usr/share/eigen3/cmake)
fi
[ -x /usr/bin/g++ ] && export CXX=/usr/bin/g++ CUDAHOSTCXX=/usr/bin/g++ CC=/usr/bin/gcc
if ! CMAKE_BUILD_PARALLEL_LEVEL=$(nproc) $PY -m pip install --no-build-isolation --no-deps -e . \
    --config-settings=cmake.define.CMAKE_CUDA_ARCHITECTURES=90 --config-settings=build-dir=build/edit-gpu \
    "${EXTRA[@]}" > "$OUT/build.log" 2>&1; then
  echo "BUILD FAILED"; tail -40 "$OUT/build.log"; exit 1
fi
echo "setup done in $(( $(date +%s) - t0 )) s; cuda_enabled=$($PY -c 'import tiger.ops as o; print(o.cuda_enabled())')"
nvidia-smi --query-gpu=name,memory.total --format=csv,noheader
$PY benchmarks/edit.py --device cuda --density 15 --guidance recolor analytic --steps 200 --size 512 \
    --json "$OUT/edit_h100_nodiffusion.json" 2>&1 | tee "$OUT/edit_h100_nodiffusion.txt"
for graph in --cuda-graph ""; do
  if $PY benchmarks/edit.py --device cuda --density 15 --guidance ip2p+mvdream --random-models full --dtype bf16 \
      --steps 1200 --size 512 --warmup 5 $graph --time-budget-s "${BUDGET_S:-150}" --json "$OUT/edit_h100.json" \
      2>&1 | grep -v -i -e "warn" -e "Model config" | tee "$OUT/edit_h100${graph:+_graph}.txt"; then
    [ -f "$OUT/edit_h100.json" ] && break
  fi
  echo "run with '${graph}' failed; trying without CUDA graphs"
done
echo "total $(( $(date +%s) - t0 )) s"
