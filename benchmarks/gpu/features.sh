#!/usr/bin/env bash
# GPU run of the language features: CUDA tests of the ops and the pipeline, then the
# per-image stage benchmark with full-size random-weight CLIP ViT-B/16 and SAM ViT-H at 1080p, and
# the mask-NMS op against LangSplat's Python loop. Run from the repo root after
# `pip install --no-build-isolation -e .` built the CUDA kernels. Results: $OUT/features.txt.
set -uo pipefail
OUT="${OUT:-outputs}"
mkdir -p "$OUT"
LOG="$OUT/features.txt"
PY="${PYTHON:-python3}"
export PYTHONUNBUFFERED=1 TOKENIZERS_PARALLELISM=false
{
  echo "== features GPU run: $(date -u)"
  nvidia-smi --query-gpu=name,memory.total --format=csv,noheader || true
  "$PY" -c "import torch, transformers, tiger; print('torch', torch.__version__, 'transformers', transformers.__version__, 'tiger CUDA kernels:', tiger.ops.cuda_enabled())"
  echo "== CUDA tests (ops: CPU vs CUDA values, gradients, opcheck; pipeline on the GPU)"
  timeout 240 "$PY" -m pytest -q -m cuda tests/language tests/models tests/ops/test_jbu.py tests/ops/test_nms.py tests/ops/test_masked_average.py -p no:cacheprovider 2>&1 | tail -25
  echo "== benchmark: feature maps at 1920x1080 (full resolution)"
  timeout 420 "$PY" -m benchmarks.features --device cuda --models full --image 1080x1920 --out-long-side 1920 2>&1
  echo "== benchmark: feature maps at 960x540 (pipeline with JBU only)"
  timeout 240 "$PY" -m benchmarks.features --device cuda --models full --image 1080x1920 --out-long-side 960 --skip-ops --steps 0 2>&1
  echo "== done: $(date -u)"
} 2>&1 | tee "$LOG"
