#!/usr/bin/env bash
# One device call for the edit-speed measurements of docs/BENCHMARKS.md ("Diffusion guidance",
# "Edit loop"): build, the CUDA tests of the guidance models' kernels, streams, CUDA graphs, GroupNorm
# and LayerNorm, memcheck of the GroupNorm and LayerNorm kernels, how the two guidances share the GPU (benchmarks.gpu.guidance_streams),
# then the 1200-step CSD edit at its defaults and with the guidances on one stream, in that order
# on one card. About 8 minutes on an H100 (build 80-100 s, each edit ~105 s).
#
# From the repo root on the device, with .whl (diffusers) and .carry/deb carried:
#   OUT=$OUT bash benchmarks/gpu/edit_speed.sh
# Results in $OUT (named as docs/BENCHMARKS.md cites them): guidance_streams_h100.txt,
# edit_1200_steps_h100.txt; logs: tests.txt, memcheck.txt, build.log. Summary on stdout.
set -uo pipefail
cd "$(dirname "$0")/../.."
OUT="${OUT:?set OUT}"
mkdir -p "$OUT"
export PYTHONUNBUFFERED=1 TOKENIZERS_PARALLELISM=false
t0=$(date +%s)
say() { echo "[$(( $(date +%s) - t0 )) s] $*"; }
CHECK_STEPS=build OUT="$OUT/check" bash benchmarks/gpu/check.sh .whl .carry/deb/libeigen3-dev_3.4.0-4_all.deb \
  > "$OUT/build.log" 2>&1
say "build: $(grep -E 'build ok|BUILD FAILED' "$OUT/check/check.log" | tail -1)"
export PYTHONPATH="/tmp/site${PYTHONPATH:+:$PYTHONPATH}"
# tests/edit/guidance as a whole: listing its files among others' can lose its conftest's fixtures
timeout 300 python3 -m pytest -q -p no:cacheprovider tests/edit/guidance tests/edit/test_csd_streams.py \
  tests/edit/test_cuda_graph.py tests/ops/test_group_norm.py tests/ops/test_layer_norm.py tests/utils/test_streams.py \
  > "$OUT/tests.txt" 2>&1
say "CUDA tests: $(tail -1 "$OUT/tests.txt")"
timeout 120 compute-sanitizer --tool memcheck --error-exitcode 9 python3 -m benchmarks.gpu.sanitize_group_norm \
  > "$OUT/memcheck.txt" 2>&1
say "memcheck rc=$? $(grep 'ERROR SUMMARY' "$OUT/memcheck.txt")"
timeout 150 compute-sanitizer --tool memcheck --error-exitcode 9 python3 -m pytest -q -p no:cacheprovider \
  tests/ops/test_layer_norm.py -k "cuda and not graph" > "$OUT/memcheck_layer_norm.txt" 2>&1
say "memcheck layer_norm rc=$? $(grep 'ERROR SUMMARY' "$OUT/memcheck_layer_norm.txt")"
# timeout -s ABRT with faulthandler: a hang prints where Python waits instead of nothing
timeout -s ABRT 180 python3 -X faulthandler -m benchmarks.gpu.guidance_streams > "$OUT/guidance_streams.log" 2>&1
say "guidance_streams rc=$?"
{ echo "# python -m benchmarks.gpu.guidance_streams, $(nvidia-smi --query-gpu=name --format=csv,noheader | head -1)"
  grep -v -i -e warn "$OUT/guidance_streams.log"; } > "$OUT/guidance_streams_h100.txt"
grep '^{' "$OUT/guidance_streams.log" | cut -c1-150
EDIT=(--device cuda --density 16 --guidance ip2p+mvdream --random-models full --dtype bf16 --steps 1200 --size 512
      --warmup 5 --cuda-graph)
{ echo "# edit loop, 1200 steps, default (pool of 256), one call: MVDream beside InstructPix2Pix on a side stream (default), then one after the other (--sequential-guidance)"
  echo "# command: python -m benchmarks.edit ${EDIT[*]} [--sequential-guidance]"; } > "$OUT/edit_1200_steps_h100.txt"
for mode in "" --sequential-guidance; do
  timeout -s ABRT 240 python3 -X faulthandler -m benchmarks.edit "${EDIT[@]}" $mode > "$OUT/edit.log" 2>&1
  say "edit ${mode:-default} rc=$?"
  grep -v -i -e warn -e "Model config" -e "it/s\]" "$OUT/edit.log" | grep -v "^\s*$" >> "$OUT/edit_1200_steps_h100.txt"
  grep '^{' "$OUT/edit.log" | python3 -c "import json, sys; d = json.loads(sys.stdin.readline()); print({k: round(v, 2)
    for k, v in d.items() if k in ('edit_s', 'guidance_ms/step', 'render_ms/step', 'backward_ms/step', 'peak_GiB',
    'locality_spread_dB', 'locality_rest_dB')})"
done
rm -f "$OUT/edit.log"
say "done"
