#!/usr/bin/env bash
# Every command's default path on the GPU, as a user runs it, on the fox capture with full-size
# random models in their real formats. One line per command: exit code and wall time; any
# non-zero exit (a crash, or a command that ran past CMD_TIMEOUT) fails the script.
#
#   bash benchmarks/gpu/default_commands.sh            # defaults throughout (hours: implicit FeatUp on 50 images)
#   QUICK=1 bash benchmarks/gpu/default_commands.sh    # the first 12 fox images, fewer steps, implicit
#                                                      # FeatUp on 2 images (each command within minutes)
#   ONLY="prepare reconstruct" QUICK=1 bash ...        # only these commands (the work folder is kept, so
#                                                      # later calls can run the commands that need its files)
#   SMOKE=1 bash benchmarks/gpu/default_commands.sh    # CPU smoke run: tiny random models, 3 fox images, a
#                                                      # few steps, small maps, implicit FeatUp left out;
#                                                      # catches the trivial crashes before a GPU run
#
# Run from the repo root after `make build`. The fox must be inside the repo on the GPU machine:
# FOX (default .carry/realscene/fox, else .carry/fox, else ../shared/data/fox). SIZE: the random
# models' size (full; tiny under SMOKE=1). Results: $OUT/default_commands.txt.
set -uo pipefail
OUT="${OUT:-outputs/default_commands}"
PY="${PYTHON:-python3}"
FOX="${FOX:-.carry/realscene/fox}"
[ -f "$FOX/transforms.json" ] || FOX=.carry/fox
[ -f "$FOX/transforms.json" ] || FOX=../shared/data/fox
CMD_TIMEOUT="${CMD_TIMEOUT:-3600}"
if [ "${SMOKE:-0}" = 1 ]; then DEVICE="${DEVICE:-cpu}"; SIZE="${SIZE:-tiny}"; fi
DEVICE="${DEVICE:-cuda}"
SIZE="${SIZE:-full}"
export TIGER_MODELS="${TIGER_MODELS:-$OUT/models}" PYTHONUNBUFFERED=1 TOKENIZERS_PARALLELISM=false
source "$(dirname "$0")/bytecode.sh"  # timed as an installation runs: byte-code compiled once
mkdir -p "$OUT"
LOG="$OUT/default_commands.txt"
W="$OUT/work"
[ -z "${ONLY:-}" ] && rm -rf "$W"
mkdir -p "$W"
FAILED=0

run() {  # run NAME ARGS...: one tiger command, its output in $W/NAME.log, one summary line
  local name=$1; shift
  if [ -n "${ONLY:-}" ] && [[ " $ONLY " != *" $name "* ]]; then return 0; fi
  if [[ " ${SKIP_CMDS:-} " == *" $name "* ]]; then printf '%-22s skipped (%s)\n' "$name" "${SKIP_WHY:-SKIP_CMDS}"; return 0; fi
  local t0=$(date +%s%N)
  timeout "$CMD_TIMEOUT" "$PY" -m tiger.cli.main "$@" > "$W/$name.log" 2>&1
  local rc=$?
  local ms=$(( ($(date +%s%N) - t0) / 1000000 ))
  printf '%-22s exit %3d  %5d.%01d s   tiger %s\n' "$name" "$rc" $((ms / 1000)) $((ms % 1000 / 100)) "$*"
  if [ "$rc" -ne 0 ]; then FAILED=1; tail -5 "$W/$name.log" | sed 's/^/    | /'; fi
}

{
  echo "== default commands on the GPU: $(date -u); fox at $FOX; QUICK=${QUICK:-0}"
  [ "$DEVICE" = cpu ] || nvidia-smi --query-gpu=name,memory.total --format=csv,noheader || true
  if [ ! -f "$TIGER_MODELS/featup/maskclip_jbu_stack_cocostuff.ckpt" ]; then
    t0=$(date +%s); "$PY" -m benchmarks.gpu.write_random_models "$TIGER_MODELS" --size "$SIZE" || FAILED=1
    echo "random $SIZE models written to $TIGER_MODELS in $(( $(date +%s) - t0 )) s"
  fi
  R=(); F=(); E=(); P=(); ED=(); Q=(); D=(); RE=()
  IMPLICIT_DATA="$FOX"
  subset() {  # subset N FOLDER: the first N frames of the fox as a capture of its own
    mkdir -p "$2"; [ -e "$2/images" ] || ln -s "$(cd "$FOX" && pwd)/images" "$2/images"
    "$PY" -c "import json; m=json.load(open('$FOX/transforms.json')); m['frames']=m['frames'][:$1]; json.dump(m, open('$2/transforms.json','w'))"
  }
  if [ "${QUICK:-0}" = 1 ]; then
    R=(--steps 3000 --downscale 2); E=(--steps 200); ED=(--steps 100)
    P=(--recon-steps 3000 --downscale 2 --upsampler jbu --embed-steps 200)
    # implicit FeatUp (about 80 s an image before its speed-up) on the first two images only
    subset 2 "$W/fox2"; IMPLICIT_DATA="$W/fox2"
    subset 12 "$W/fox12"; FOX="$W/fox12"   # SAM ViT-H takes ~7.5 s an image at 1080p
  fi
  if [ "${SMOKE:-0}" = 1 ]; then  # every command's code path, none of its cost: tiny models, tiny maps
    # edit: the recolor guidance; the tiny VAE (factor 2) turns InstructPix2Pix's 512-px input into
    # 256x256 latents whose mid-block attention asks for 64 GiB on the CPU
    # edit and delete with --force: a tiny random CLIP's "fox" selects most of the scene, which the
    # commands rightly refuse without it (the selection guard); the smoke run is after their code paths
    R=(--steps 30 --downscale 8 --init-points 3000); E=(--steps 10); ED=(--steps 2 --size 64 --guidance recolor --color orange --force)
    F=(--long-side 96 --clip-long-side 64 --pca-dim 16)
    P=(--recon-steps 30 --downscale 8 --init-points 3000 --upsampler jbu "${F[@]}" --embed-steps 10)
    Q=(--views 1); D=(--steps 2 --downscale 8 --force); RE=(--views 2 --downscale 8)
    subset 3 "$W/fox3"; FOX="$W/fox3"
    # implicit FeatUp's 1200-step fit takes over 15 minutes of CPU even with tiny models;
    # tests/language/test_featup_implicit.py runs its code path on the CPU
    SKIP_CMDS="features_implicit"; SKIP_WHY="SMOKE: the implicit fit is GPU work"
  fi
  run prepare        prepare "$FOX" --out "$W/prepared" --device "$DEVICE" "${P[@]}"
  [ -f "$W/prepare.log" ] && sed -n '/^tiger prepare:/,$p' "$W/prepare.log"
  run reconstruct    reconstruct "$FOX" --out "$W/recon" --device "$DEVICE" "${R[@]}"
  grep -h "test views" "$W/reconstruct.log" 2>/dev/null
  run features_implicit features "$IMPLICIT_DATA" --out "$W/feat_implicit" --device "$DEVICE" "${F[@]}"
  run features_jbu   features "$FOX" --out "$W/feat_jbu" --upsampler jbu --device "$DEVICE" "${F[@]}"
  run features_bilinear features "$FOX" --out "$W/feat_bilinear" --upsampler bilinear --device "$DEVICE" "${F[@]}"
  run embed          embed "$W/recon/scene.ply" "$FOX" --features "$W/feat_jbu" --out "$W/scene_lang.ply" --device "$DEVICE" "${E[@]}"
  run query          query "$W/scene_lang.ply" "fox" --data "$FOX" --out "$W/query" --device "$DEVICE" "${Q[@]}"
  run query_prepared query "$W/prepared" "fox" --data "$FOX" --out "$W/query_prepared" --device "$DEVICE" "${Q[@]}"
  run edit           edit "$W/scene_lang.ply" "make it look like a tiger" --target "fox" --out "$W/edit" --device "$DEVICE" "${ED[@]}"
  run delete         delete "$W/scene_lang.ply" "fox" --data "$FOX" --out "$W/delete" --device "$DEVICE" "${D[@]}"
  run render         render "$W/scene_lang.ply" --data "$FOX" --out "$W/render" --device "$DEVICE" "${RE[@]}"
  echo "== done: $(date -u); $([ $FAILED = 0 ] && echo 'all commands exited 0' || echo 'FAILED')"
} 2>&1 | tee "$LOG"
grep -q "all commands exited 0" "$LOG"
