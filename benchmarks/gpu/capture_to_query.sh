#!/usr/bin/env bash
# The path from photos to a queryable scene and the viewer, on one GPU: `tiger reconstruct` on the
# fox at its defaults (half resolution, 7000 steps; held-out PSNR), the language field loop as
# `tiger embed` runs it at its defaults (fox-sized maps), training-free lifting at fox scale, the per-image
# language-feature stages (implicit FeatUp; the SAM mask path) and the viewer's frame loop.
#
# Usage, from the repo root with .whl and .carry carried (after a build, e.g. check.sh's):
#   OUT=$OUT bash benchmarks/gpu/capture_to_query.sh
# Environment: FOX (default .carry/realscene/fox), ONLY (space-separated subset of the step names
# below), TIMEOUT_SCALE (multiplies every step's time limit).
set -uo pipefail
cd "$(dirname "$0")/../.."
OUT="${OUT:?set OUT}"
FOX="${FOX:-.carry/realscene/fox}"
ONLY="${ONLY:-reconstruct embed lift featup masks viewer}"
export PYTHONUNBUFFERED=1 TOKENIZERS_PARALLELISM=false PYTHONPATH="/tmp/site${PYTHONPATH:+:$PYTHONPATH}"
mkdir -p "$OUT"
source benchmarks/gpu/bytecode.sh  # timed as an installation runs: byte-code compiled once
say() { echo "[$(date -u +%H:%M:%S)] $*" | tee -a "$OUT/log.txt"; }
step() {  # name, seconds, command...
  local name=$1 limit=$2; shift 2
  [[ " $ONLY " == *" $name "* ]] || return 0
  local t0=$(date +%s)
  timeout "$(( limit * ${TIMEOUT_SCALE:-1} ))" "$@" > "$OUT/$name.txt" 2>&1
  local rc=$?
  say "$name rc=$rc in $(( $(date +%s) - t0 )) s"
  grep -v -i -e "warn" -e "it/s\]" "$OUT/$name.txt" | tail -"${TAIL:-14}" | tee -a "$OUT/log.txt"
}
say "GPU: $(nvidia-smi --query-gpu=name --format=csv,noheader)"
step reconstruct 150 python3 -m tiger.cli.main reconstruct "$FOX" --out /tmp/fox_recon --device cuda \
  --steps 7000 --downscale 2 --force
[ -f /tmp/fox_recon/metrics.json ] && cp /tmp/fox_recon/metrics.json "$OUT/reconstruct_metrics.json"
step embed 120 python3 -m benchmarks.language_field --device cuda --only loop --loop-reference-steps 0
step lift 90 python3 -m benchmarks.lift --device cuda --gaussians 250000 --views 43 --size 1080x1920
step featup 200 python3 -m benchmarks.featup_implicit --device cuda
step masks 120 python3 -m benchmarks.masks --device cuda --models full --image 1080x1920 --mask-counts 100,300,1000
step viewer 90 python3 -m benchmarks.viewer --scene heavy --n 1000000 --device cuda --iters 20 \
  --out "$OUT/viewer_h100.json"
