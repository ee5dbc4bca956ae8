#!/usr/bin/env bash
# GPU run for the scene/recon area (one H100, after `pip install --no-build-isolation -e .`).
# Run from the repo root; writes "$OUT/scene.txt" (and scene_fox.json). About 4 minutes:
#   1. the CUDA tests of tests/scene and tests/recon (pytest -m cuda),
#   2. the fox capture fitted at half resolution (540x960) on the GPU, as many steps of a
#      7000-step schedule as fit in 200 s of training, held-out PSNR/SSIM against steps/time.
# The fox images are looked up in $FOX_DATA, ../shared/data/fox, then shared/data/fox.
set -uo pipefail
OUT="${OUT:-outputs/gpu}"
mkdir -p "$OUT"
LOG="$OUT/scene.txt"
PY="${PYTHON:-python}"
export PYTHONUNBUFFERED=1
{
  echo "== scene/recon GPU run: $(date -u)"
  nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader || true
  "$PY" -c "import torch, tiger.ops as o; print('torch', torch.__version__, 'cuda', torch.version.cuda, \
'| tiger CUDA kernels:', o.cuda_enabled())"

  echo; echo "== 1. CUDA tests (tests/scene, tests/recon)"
  timeout 300 "$PY" -m pytest -q -m cuda tests/scene tests/recon -p no:cacheprovider -rs 2>&1 | tail -20

  echo; echo "== 2. fox at half resolution on the GPU"
  FOX=""
  for d in "${FOX_DATA:-}" ../shared/data/fox shared/data/fox; do
    if [ -n "$d" ] && [ -f "$d/transforms.json" ]; then FOX="$d"; break; fi
  done
  if [ -z "$FOX" ]; then
    echo "SKIPPED: fox data not found (set FOX_DATA to a folder with transforms.json and images/)"
  else
    # The rasterizer's CUDA kernels may not have landed yet: then the same half-resolution
    # fit runs on this machine's CPU cores instead (said so in the output).
    if "$PY" -c "import sys, torch, tiger; sys.exit(0 if torch.cuda.is_available() and \
torch._C._dispatch_has_kernel_for_dispatch_key('tiger::rasterize', 'CUDA') else 1)"; then
      DEV=cuda; ITERS=7000
    else
      echo "NOTE: no CUDA kernel for tiger::rasterize in this build: fitting on the CPU ($(nproc) cores)"
      DEV=cpu; ITERS=1500
    fi
    timeout 420 "$PY" -m benchmarks.recon_fox --data "$FOX" --device "$DEV" --downscale 2 \
      --iterations "$ITERS" --time-budget 200 --eval-every 500 --init-points 50000 --max-gaussians 2000000 \
      --cache /tmp/tiger_fox_cache --out /tmp/tiger_fox_gpu --json "$OUT/scene_fox.json" 2>&1 \
      | grep -v "it/s\]" | tail -40
  fi
  echo; echo "== done: $(date -u)"
} 2>&1 | tee "$LOG"
