#!/usr/bin/env bash
# GPU run of the retrieval area (relevancy op CUDA kernels; language field training).
# Run from anywhere on a machine with one GPU after `pip install --no-build-isolation -e .`
# has built the CUDA kernels; writes "$OUT/retrieval.txt" (OUT defaults to outputs/gpu).
# Budget: under 4 minutes (each step has its own timeout).
set -uo pipefail
cd "$(dirname "$0")/../.."
OUT="${OUT:-outputs/gpu}"
mkdir -p "$OUT"
PY="${PYTHON:-python}"
LOG="$OUT/retrieval.txt"
{
  echo "== retrieval GPU run, $(date -u +%FT%TZ), commit $(git rev-parse --short HEAD 2>/dev/null || echo '?')"
  nvidia-smi --query-gpu=name,memory.total,clocks.max.memory --format=csv 2>/dev/null || true
  $PY -c "import torch, tiger; print('torch', torch.__version__, 'cuda', torch.version.cuda, '| tiger CUDA kernels:', tiger.ops.cuda_enabled())"

  echo; echo "== CUDA tests (relevancy op: CPU vs CUDA, fp16/fp32/fp64, vector and generic paths, opcheck, grad)"
  timeout 150 $PY -m pytest -q -p no:cacheprovider -m cuda tests/ops/test_relevancy.py tests/retrieval/test_retrieval.py 2>&1 | tail -25
  echo "pytest exit: ${PIPESTATUS[0]}"

  echo; echo "== relevancy op throughput vs the bandwidth floor (acceptance: fp16 1e7 x 64 within 2x)"
  timeout 120 $PY -m benchmarks.relevancy --device cuda 2>&1
  echo "exit: $?"

  echo; echo "== language field: per-step time (features-only vs full backward) and convergence"
  timeout 120 $PY -m benchmarks.language_field --device cuda --steps 100 2>&1
  echo "exit: $?"
} 2>&1 | tee "$LOG"
