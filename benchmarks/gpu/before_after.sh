#!/usr/bin/env bash
# The same GPU benchmarks on an earlier tree and on this one, in one call on one card, so a change
# can be shown to cost nothing: the rasterizer on real-scene distributions (benchmarks/gpu/real_scenes.py,
# gsplat left out) and the CSD edit with full-size random InstructPix2Pix + MVDream
# (benchmarks/edit.py). The earlier tree is built and measured first, then this tree is built
# (its editable install replaces the earlier one) and measured.
#
# Usage, from the repo root on a machine with one GPU, with .whl (diffusers) and .carry carried:
#   BASE=.carry/base OUT=$OUT bash benchmarks/gpu/before_after.sh
# Environment: EDIT_STEPS (default 300), CASES (default snowmiku-1080p,standard,heavy),
#   SNOWMIKU (default .carry/realscene/snowmiku), WHEELS (.whl), EIGEN_DEB.
# Results: $OUT/{before,after}_real_scenes.txt, $OUT/{before,after}_edit.{txt,json}, $OUT/log.txt.
set -uo pipefail
cd "$(dirname "$0")/../.."
REPO=$(pwd)
OUT="${OUT:?set OUT}"
BASE="$(cd "${BASE:?set BASE to the earlier tree}" && pwd)"
WHEELS="$(cd "${WHEELS:-.whl}" && pwd)"
EIGEN_DEB="$(realpath "${EIGEN_DEB:-.carry/deb/libeigen3-dev_3.4.0-4_all.deb}")"
SNOWMIKU="$(cd "${SNOWMIKU:-.carry/realscene/snowmiku}" && pwd)"
CASES="${CASES:-snowmiku-1080p,standard,heavy}"
STEPS="${EDIT_STEPS:-300}"
export PYTHONUNBUFFERED=1 TOKENIZERS_PARALLELISM=false PYTHONPATH="/tmp/site${PYTHONPATH:+:$PYTHONPATH}"
mkdir -p "$OUT"
say() { echo "[$(date -u +%H:%M:%S)] $*" | tee -a "$OUT/log.txt"; }
EDIT_ARGS=(--device cuda --density 16 --guidance ip2p+mvdream --random-models full --dtype bf16
           --steps "$STEPS" --size 512 --warmup 5 --cuda-graph)

bench() {  # the command words that run a benchmark file of the current tree (a module where it has packages)
  local file=$1 mod=${1%.py}
  if [ -f benchmarks/__init__.py ]; then echo "python3 -m ${mod//\//.}"; else echo "python3 $file"; fi
}

measure() {  # $1 = before|after; run from the tree's root
  local tag=$1
  CHECK_STEPS=build OUT="$OUT/$tag" bash benchmarks/gpu/check.sh "$WHEELS" "$EIGEN_DEB" >/dev/null 2>&1
  say "$tag build: $(grep -E 'build ok|BUILD FAILED' "$OUT/$tag/check.log" | tail -1)"
  timeout 200 $(bench benchmarks/gpu/real_scenes.py) --cases "$CASES" --no-gsplat --snowmiku "$SNOWMIKU" \
    --out "$OUT/$tag" > "$OUT/${tag}_real_scenes.txt" 2>&1
  say "$tag real_scenes rc=$?"
  sed -n '/^== Speed/,/^== Per-stage/p' "$OUT/${tag}_real_scenes.txt" | tee -a "$OUT/log.txt"
  timeout 240 $(bench benchmarks/edit.py) "${EDIT_ARGS[@]}" --json "$OUT/${tag}_edit.json" > "$OUT/${tag}_edit.txt" 2>&1
  say "$tag edit rc=$?"; grep -v -i -e "warn" -e "Model config" "$OUT/${tag}_edit.txt" | tail -8 | tee -a "$OUT/log.txt"
}

say "GPU: $(nvidia-smi --query-gpu=name --format=csv,noheader)"
(cd "$BASE" && measure before)
cd "$REPO" && measure after
