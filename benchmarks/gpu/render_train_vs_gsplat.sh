#!/usr/bin/env bash
# The rendering core and the training step against gsplat on one GPU, in two parts (each fits one
# device call of 10 minutes):
#   PART=a: build, the CUDA tests of ops/render/recon, compute-sanitizer memcheck (every kernel of
#           sanitize_case.py: the rendering core and the fused SSIM) and racecheck (rasterizer,
#           binning, SSIM, SH), the SH benchmark (staged default vs plain kernels, sh.py --plain, beside
#           gsplat) and the SSIM benchmark at 1080p.
#   PART=b: build, the same CUDA tests (TESTS=0 skips them), the sanitizer runs of part a with
#           SANITIZE=1 (RACECHECK: the kernel-name filters), benchmarks/gpu/real_scenes.py (ours vs gsplat per stage; tile-sort size
#           sweep SORT_KEYS_SWEEP; REAL_BEFORE: the kernel choices of its 'before' columns, e.g. binning.path=global; REAL_CASES= (empty)
#           skips it) and benchmarks/gpu/train_vs_gsplat.py on the fox at full resolution
#           (TRAIN=0 skips it; TRAIN_ABLATION: ';'-separated kernel choices, e.g.
#           kernels.backward_pixels_per_thread=1, one more run of ours with each).
# gsplat JIT-compiles on first use (~90 s): its build folder is packed into $OUT/gsplat_ext.tgz and,
# carried back as .carry/gsplat_ext.tgz, reused (same wheel, same paths).
# From the repo root with .whl, .carry/deb and .carry/realscene carried. Results: $OUT/vs_gsplat_<part>.tgz.
cd "$(dirname "$0")/../.."
export PYTHONUNBUFFERED=1 TORCH_CUDA_ARCH_LIST=9.0 MAX_JOBS="$(nproc)"
PART="${PART:-a}"
R="$OUT/vs_gsplat_$PART"
mkdir -p "$R"
say() { echo "[$(date -u +%H:%M:%S)] $*" | tee -a "$R/log.txt"; }
CHECK_STEPS=build OUT="$R" bash benchmarks/gpu/check.sh .whl .carry/deb/libeigen3-dev_3.4.0-4_all.deb >/dev/null 2>&1
say "build: $(tail -1 "$R/check.log")"
export PYTHONPATH="/tmp/site${PYTHONPATH:+:$PYTHONPATH}"
export TORCH_EXTENSIONS_DIR=/tmp/torch_ext
mkdir -p "$TORCH_EXTENSIONS_DIR"
[ -f .carry/gsplat_ext.tgz ] && tar xzf .carry/gsplat_ext.tgz -C "$TORCH_EXTENSIONS_DIR" && say "gsplat build reused"
SAN="$(command -v compute-sanitizer || echo /usr/local/cuda/bin/compute-sanitizer)"
if [ "${TESTS:-1}" = 1 ]; then
  timeout "${TESTS_TIMEOUT:-200}" python3 -m pytest -q -p no:cacheprovider tests/ops tests/render tests/recon \
    > "$R/tests.log" 2>&1
  say "tests rc=$?: $(tail -1 "$R/tests.log")"; grep -E "^(FAILED|ERROR)" "$R/tests.log" | head | tee -a "$R/log.txt"
fi
if [ "$PART" = a ] || [ "${SANITIZE:-0}" = 1 ]; then
  PYTORCH_NO_CUDA_MEMORY_CACHING=1 timeout 200 "$SAN" --tool memcheck --error-exitcode 99 \
    python3 -m benchmarks.gpu.sanitize_case > "$R/memcheck.log" 2>&1
  say "memcheck rc=$?: $(grep -E 'ERROR SUMMARY' "$R/memcheck.log" | tail -1)"
  for kns in ${RACECHECK:-raster_cuda bin_cuda ssim sh_}; do
    timeout 150 "$SAN" --tool racecheck --error-exitcode 99 --kernel-name kns=$kns \
      python3 -m benchmarks.gpu.sanitize_case > "$R/racecheck_$kns.log" 2>&1
    say "racecheck $kns rc=$?: $(grep -E 'RACECHECK SUMMARY|ERROR SUMMARY' "$R/racecheck_$kns.log" | tail -1)"
  done
fi
if [ "$PART" = a ]; then
  PYTORCH_NO_CUDA_MEMORY_CACHING=1 timeout 120 "$SAN" --tool memcheck --target-processes all --error-exitcode 99 \
    --kernel-name kns=sh_ python3 -m pytest -q -p no:cacheprovider tests/ops/test_sh.py -k staged > "$R/memcheck_sh.log" 2>&1
  say "memcheck sh rc=$?: $(grep -E 'ERROR SUMMARY' "$R/memcheck_sh.log" | tail -1); $(tail -1 "$R/memcheck_sh.log")"
  timeout 120 "$SAN" --tool racecheck --target-processes all --error-exitcode 99 --kernel-name kns=sh_ \
    python3 -m pytest -q -p no:cacheprovider tests/ops/test_sh.py -k staged > "$R/racecheck_sh.log" 2>&1
  say "racecheck sh rc=$?: $(grep -E 'RACECHECK SUMMARY' "$R/racecheck_sh.log" | tail -1)"
  for kernels in staged plain; do
    timeout 200 python3 -m benchmarks.sh --device cuda --n 1e5 1e6 4e6 $([ $kernels = plain ] && echo --plain) \
      > "$R/sh_$kernels.txt" 2>&1
    say "sh.py, $kernels kernels rc=$?"; tail -6 "$R/sh_$kernels.txt" | tee -a "$R/log.txt"
  done
  timeout 100 python3 -m benchmarks.recon_ssim --device cuda --sizes 540x960,1080x1920 \
    --methods fused,depthwise,conv > "$R/ssim.txt" 2>&1
  say "recon_ssim rc=$?"; tail -3 "$R/ssim.txt" | tee -a "$R/log.txt"
else
  if [ -n "${REAL_CASES-x}" ]; then
    timeout "${REAL_TIMEOUT:-280}" python3 -m benchmarks.gpu.real_scenes --out "$R" \
      --cases "${REAL_CASES:-snowmiku-1080p,standard,heavy}" --sort-keys-sweep "${SORT_KEYS_SWEEP-1024,2048}" \
      --before "${REAL_BEFORE:-binning._serial=true}" --fox-data .carry/realscene/fox > "$R/real_scenes.txt" 2>&1
    say "real_scenes rc=$?"; sed -n '/^== Speed/,$p' "$R/real_scenes.txt" | tee -a "$R/log.txt"
  fi
  if [ "${TRAIN:-1}" = 1 ]; then
    ablations=()
    IFS=';' read -ra abl <<< "${TRAIN_ABLATION:-}"
    for x in "${abl[@]}"; do [ -n "$x" ] && ablations+=(--ablation "$x"); done
    timeout "${TRAIN_TIMEOUT:-240}" python3 -m benchmarks.gpu.train_vs_gsplat --data .carry/realscene/fox \
      "${ablations[@]}" --json "$R/train_vs_gsplat.json" > "$R/train_vs_gsplat.txt" 2>&1
    say "train_vs_gsplat rc=$?"; sed -n '/^== Training/,$p' "$R/train_vs_gsplat.txt" | tee -a "$R/log.txt"
  fi
fi
(cd "$TORCH_EXTENSIONS_DIR" && [ -n "$(ls)" ] && tar czf "$OUT/gsplat_ext.tgz" .)
(cd "$OUT" && tar czf "vs_gsplat_$PART.tgz" "vs_gsplat_$PART" && rm -rf "vs_gsplat_$PART")
ls -la "$OUT"
