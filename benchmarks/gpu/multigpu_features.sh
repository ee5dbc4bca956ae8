#!/usr/bin/env bash
# extract_features on 1 GPU vs 2 GPUs (torchrun, NCCL) in one device call on `nvidia-h200-x2`:
#   1. build tiger with CUDA (benchmarks/gpu/check.sh CHECK_STEPS=build)
#   2. full-size random-weight CLIP ViT-B/16 + SAM ViT-H + JBU, N synthetic 1920x1080 images
#   3. single process on GPU 0
#   4. torchrun --nproc_per_node 2 (NCCL, one rank per GPU)
#   5. every written tensor of the 2-GPU run compared with the single-process run
#   6. single process again, compared too (the run-to-run baseline)
# About 6 minutes at 24 images (build 60 s, models 25 s, each run 70-85 s, each comparison ~30 s):
# give the call 420 s or more.
# Results under $OUT: multigpu.log, single*.json, two_gpu.json, compare.txt.
# Usage, from the repo root:  OUT=/tmp/out [SKIP_AGAIN=1] bash benchmarks/gpu/multigpu_features.sh EIGEN_DEB [N_IMAGES]
set -uo pipefail
cd "$(dirname "$0")/../.."
OUT="${OUT:-/tmp/tiger-multigpu}"
mkdir -p "$OUT"
EIGEN_DEB="${1:-}"
N="${2:-32}"
PY="${PYTHON:-python3}"
WORK=/tmp/tiger-multigpu-work
LOG="$OUT/multigpu.log"
# NVLink multicast stays off (KINDS.md: it can take the host's shared GPUs out of service).
export NCCL_NVLS_ENABLE=0 TORCH_SYMM_MEM_DISABLE_MULTICAST=1 NVSHMEM_DISABLE_NVLS=1
export PYTHONUNBUFFERED=1 TOKENIZERS_PARALLELISM=false OMP_NUM_THREADS=8
el() { awk -v a="$1" -v b="$(date +%s.%N)" 'BEGIN { printf "%.1f", b - a }'; }
say() { echo "[$(date -u +%H:%M:%S)] $*" | tee -a "$LOG"; }

say "GPUs: $(nvidia-smi --query-gpu=index,name,memory.total --format=csv,noheader | tr '\n' ';')"
nvidia-smi topo -m >> "$LOG" 2>&1
OUT="$OUT/build" CHECK_STEPS=build bash benchmarks/gpu/check.sh "" "$EIGEN_DEB" >> "$LOG" 2>&1 || { say "build failed"; exit 1; }
say "build ok: cuda_enabled=$($PY -c 'import tiger.ops as o; print(o.cuda_enabled())')"

t0=$(date +%s.%N)
$PY -m benchmarks.multigpu_features prepare "$WORK" --images "$N" >> "$LOG" 2>&1 || { say "prepare failed"; tail -30 "$LOG"; exit 1; }
say "prepared in $(el "$t0") s"

t0=$(date +%s.%N)
CUDA_VISIBLE_DEVICES=0 timeout 90 $PY -m benchmarks.multigpu_features run "$WORK" single >> "$LOG" 2>&1
say "single (1 process, GPU 0) rc=$? wall $(el "$t0") s"
cp "$WORK/single/timing.json" "$OUT/single.json" 2>/dev/null

t0=$(date +%s.%N)
timeout 90 $PY -m torch.distributed.run --standalone --nproc_per_node 2 \
  -m benchmarks.multigpu_features run "$WORK" two_gpu >> "$LOG" 2>&1
say "two_gpu (torchrun, 2 ranks) rc=$? wall $(el "$t0") s"
cp "$WORK/two_gpu/timing.json" "$OUT/two_gpu.json" 2>/dev/null


# The comparison that matters first (one comparison reads ~50 files: ~30 s at 24 images).
$PY -m benchmarks.multigpu_features compare "$WORK" single two_gpu > "$OUT/compare.txt" 2>&1
say "compare two_gpu rc=$?"

if [ -z "${SKIP_AGAIN:-}" ]; then  # the run-to-run baseline (SKIP_AGAIN=1 leaves it out)
t0=$(date +%s.%N)
CUDA_VISIBLE_DEVICES=0 timeout 90 $PY -m benchmarks.multigpu_features run "$WORK" single_again >> "$LOG" 2>&1
say "single_again (1 process, GPU 0) rc=$? wall $(el "$t0") s"
cp "$WORK/single_again/timing.json" "$OUT/single_again.json" 2>/dev/null
$PY -m benchmarks.multigpu_features compare "$WORK" single single_again >> "$OUT/compare.txt" 2>&1
say "compare single_again rc=$?"
fi
cat "$OUT/compare.txt" | tee -a "$LOG"
$PY - "$OUT" <<'EOF' | tee -a "$LOG"
import json, sys, pathlib
out = pathlib.Path(sys.argv[1])
rows = {n: json.loads((out / f"{n}.json").read_text()) for n in ("single", "two_gpu", "single_again") if (out / f"{n}.json").is_file()}
print("| run | GPUs | backend | images | extract s | images/s | model load s |")
print("| --- | ---: | --- | ---: | ---: | ---: | ---: |")
for n, r in rows.items():
    print(f"| {n} | {r['world_size']} | {r['backend']} | {r['images']} | {r['extract_s']:.2f} | {r['images_per_s']:.2f} | {r['model_load_s']:.1f} |")
EOF
say "done"
