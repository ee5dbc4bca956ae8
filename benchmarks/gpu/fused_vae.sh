#!/usr/bin/env bash
# One device call: does tiger's fused GroupNorm+SiLU in channels-last speed up the graphed guidance step and
# the edit loop? benchmarks/guidance.py --quick with torch's GroupNorm, the VAEs fused (the loaders' earlier
# default on CUDA) and the UNets fused too (bf16; eager and graph), then a CSD edit with the loaders'
# default (edit.sh's settings, BUDGET_S), then PROFILE_STEPS steps under torch.profiler (host vs GPU per stage).
# From the repo root with .whl and .carry/deb carried; results under $OUT. FUSED: the guidance levels.
cd "$(dirname "$0")/../.."
export OUT="${OUT:-outputs}" PYTHONUNBUFFERED=1 TOKENIZERS_PARALLELISM=false
CHECK_STEPS=build bash benchmarks/gpu/check.sh .whl .carry/deb/libeigen3-dev_3.4.0-4_all.deb >/dev/null 2>&1
tail -1 "$OUT/check.log"
export PYTHONPATH="/tmp/site${PYTHONPATH:+:$PYTHONPATH}"
echo "guidance $(date -u +%T)"
timeout 200 python3 -m benchmarks.guidance --device cuda --dtypes bf16 --modes graph,eager --quick \
  --fused "${FUSED:-off,vae,all}" --budget-s 200 --out "$OUT/guidance_fused.json" --profile-dir "$OUT" 2>&1 \
  | grep -v -i -e warn -e "Model config" > "$OUT/guidance_fused.txt"
tail -9 "$OUT/guidance_fused.txt"
echo "edit $(date -u +%T)"
timeout ${EDIT_TIMEOUT:-240} python3 -m benchmarks.edit --device cuda --density 16 --guidance ip2p+mvdream --random-models full \
  --dtype bf16 --steps 1200 --size 512 --warmup 5 --cuda-graph --view-pool 64 --fused-norms auto \
  --time-budget-s "${BUDGET_S:-120}" --profile-steps "${PROFILE_STEPS:-0}" --profile-out "$OUT/edit_profile.txt" \
  --json "$OUT/edit_fused.json" 2>&1 | grep -v -i -e warn -e "Model config" \
  > "$OUT/edit_fused.txt"
tail -4 "$OUT/edit_fused.txt"
(cd "$OUT" && tar czf profiles.tgz profile_*.txt && rm -f profile_*.txt)  # the device returns few files
echo "end $(date -u +%T)"
