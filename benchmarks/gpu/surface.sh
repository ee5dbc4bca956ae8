#!/usr/bin/env bash
# GPU smoke run of the examples (examples/*.py) on CUDA, with timings; results -> $OUT/surface.txt.
# Run from the repo root after `pip install --no-build-isolation -e .` built the CUDA kernels.
# Under 4 minutes on one H100: a 20k-Gaussian tabletop turntable (60 views, 640x480), the full
# embed-and-query pipeline with tiny random-init CLIP/SAM, and the LERF evaluation example.
set -u
OUT="${OUT:-outputs/gpu}"
mkdir -p "$OUT"
RES="$OUT/surface.txt"
TMP="$(mktemp -d)"
PY="${PYTHON:-python}"
: > "$RES"
log() { echo "$*" | tee -a "$RES"; }
timed() {  # name, command...
  local name="$1"; shift
  local t0=$(date +%s%N)
  "$@" > "$TMP/$name.log" 2>&1
  local rc=$?
  local t1=$(date +%s%N)
  local ms=$(( (t1 - t0) / 1000000 ))
  log "$(printf '| %-28s | rc %3d | %5d.%03d s |' "$name" "$rc" $((ms / 1000)) $((ms % 1000)))"
  if [ $rc -ne 0 ]; then tail -n 30 "$TMP/$name.log" | tee -a "$RES"; fi
  tail -n 3 "$TMP/$name.log" >> "$RES"
}

log "# surface: examples on $( $PY -c 'import torch; print(torch.cuda.get_device_name(0) if torch.cuda.is_available() else "NO CUDA")' )"
$PY - "$TMP" <<'PYEOF'
import sys, torch
from pathlib import Path
from tiger.demo import tabletop_scene
from tiger.scene import GaussianScene
from tiger.scene.sh import rgb_to_sh
from tests.test_examples import write_colmap_text, write_lerf_fixture
tmp = Path(sys.argv[1])
lab = tabletop_scene(1.0)
s = GaussianScene(means=lab.means, log_scales=lab.scales.log(), quats=lab.quats,
                  opacity_logits=torch.logit(lab.opacities.clamp(1e-6, 1 - 1e-6)), sh_dc=rgb_to_sh(lab.rgb))
s.save_ply(tmp / "tabletop.ply")
write_colmap_text(tmp / "colmap", lab, s, n=6, w=320, h=240)
ls = write_lerf_fixture(tmp / "lerf", "toyroom", 0, size=256, views=6)
torch.save(dict(ls.encoder.table), tmp / "text.pt")
print("inputs ready:", len(s), "Gaussians")
PYEOF

log "| example                      | status | wall      |"
timed turntable_cuda $PY examples/render_turntable.py "$TMP/tabletop.ply" --out "$TMP/tt" --views 60 \
  --width 640 --height 480 --device cuda --center 0 -0.2 0 --radius 3
timed embed_query_cuda_random $PY examples/embed_and_query_colmap.py "$TMP/colmap" "$TMP/tabletop.ply" \
  --out "$TMP/eq" --random-models --query mug --query ball --upsampler bilinear --sam-points 8 \
  --clip-long-side 224 --feature-long-side 160 --steps 500 --device cuda
timed evaluate_lerf_cuda $PY examples/evaluate_lerf.py "$TMP/lerf" \
  --ply "$TMP/lerf/outputs/{scene}/scene_lang.ply" --out "$TMP/lerf_out" --text-embeddings "$TMP/text.pt" \
  --device cuda
log ""
log "## examples and notebooks tests (CPU paths; CUDA machine)"
timeout 150 $PY -m pytest -q -x tests/test_examples.py tests/test_notebooks.py 2>&1 | tail -n 5 | tee -a "$RES"
rm -rf "$TMP"
