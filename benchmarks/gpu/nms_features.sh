#!/usr/bin/env bash
# GPU run of the mask-NMS table and the per-image feature pipeline on SAM-like mask sets
# builds tiger with CUDA through check.sh, then one benchmarks/features.py run
# (pipeline with JBU, ops, mask NMS at 100/300/1000 masks with full pairwise baselines; LangSplat's
# loop as written last, so a time-out loses only its largest rows). Results: $OUT/features_nms.txt.
# Usage, from the repo root: OUT=/tmp/out bash benchmarks/gpu/nms_features.sh [EIGEN_DEB] [SECONDS]
set -uo pipefail
cd "$(dirname "$0")/../.."
OUT="${OUT:-/tmp/tiger-nms}"
mkdir -p "$OUT"
t0=$(date +%s)
CHECK_STEPS=build bash benchmarks/gpu/check.sh "" "${1:-}" || exit 1
left=$(( ${2:-460} - ($(date +%s) - t0) ))
export PYTHONUNBUFFERED=1 TOKENIZERS_PARALLELISM=false
{
  echo "== $(date -u); $(nvidia-smi --query-gpu=name,memory.total --format=csv,noheader)"
  echo "== command: python3 -m benchmarks.features --device cuda --models full --image 1080x1920 --out-long-side 1920 --steps 0 --langsplat-max ${LANGSPLAT_MAX:-1000} (time limit ${left} s)"
  timeout "$left" python3 -m benchmarks.features --device cuda --models full --image 1080x1920 \
    --out-long-side 1920 --steps 0 --langsplat-max "${LANGSPLAT_MAX:-1000}" 2>&1
  echo "== exit $? at $(date -u)"
} > "$OUT/features_nms.txt"
tail -5 "$OUT/features_nms.txt"
