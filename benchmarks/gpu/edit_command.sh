#!/usr/bin/env bash
# `tiger edit` end to end on the GPU, as a user runs it: the fox of default_commands.sh's QUICK run
# (reconstructed, features, embedded; full-size random models in their real formats), then
# `python -m benchmarks.edit_command` (wall time by phase) RUNS times, each a fresh process, with
# the Python byte-code compiled once beforehand as an installation has it (bytecode.sh).
#
#   OUT=/tmp/ec bash benchmarks/gpu/edit_command.sh          # from the repo root, after `make build`
#
# Environment: OUT (results and work folder), RUNS (default 2), EDIT_ARGS (more `tiger edit` options).
set -uo pipefail
OUT="${OUT:-outputs/edit_command}"
PY="${PYTHON:-python3}"
RUNS="${RUNS:-2}"
export PYTHONUNBUFFERED=1 TOKENIZERS_PARALLELISM=false
mkdir -p "$OUT"
source "$(dirname "$0")/bytecode.sh"  # timed as an installation runs: byte-code compiled once
OUT="$OUT" ONLY="reconstruct features_jbu embed" QUICK=1 bash benchmarks/gpu/default_commands.sh > "$OUT/prepare.txt" 2>&1 \
  || { echo "preparing the fox failed: $OUT/prepare.txt"; exit 1; }
export TIGER_MODELS="$OUT/models"
for k in $(seq 1 "$RUNS"); do
  "$PY" -m benchmarks.edit_command "$OUT/work/scene_lang.ply" "make it look like a tiger" --target fox \
    --out "$OUT/edit$k" --device cuda --force ${EDIT_ARGS:-} > "$OUT/edit$k.txt" 2>&1
  echo "== run $k (exit $?)"; sed -n '/wall time by phase/,$p' "$OUT/edit$k.txt"
done
