#!/usr/bin/env bash
# One device call (session 5): build, the recon/guidance CUDA tests, SSIM filter timings, train_vs_gsplat and the
# graphed/eager bf16 guidance. From the repo root with .whl, .carry/deb and .carry/realscene carried.
cd "$(dirname "$0")/../.."
export OUT; CHECK_STEPS=build bash benchmarks/gpu/check.sh .whl .carry/deb/libeigen3-dev_3.4.0-4_all.deb >/dev/null 2>&1; tail -1 $OUT/check.log
export PYTHONPATH=/tmp/site TOKENIZERS_PARALLELISM=false
timeout 120 python3 -m pytest -q -p no:cacheprovider tests/utils tests/recon tests/edit/test_cuda_graph.py tests/ops/test_group_norm.py tests/edit/test_fused_norms.py > $OUT/tests.log 2>&1; echo "tests rc=$? $(tail -1 $OUT/tests.log)"; grep -E "^(FAILED|ERROR)" $OUT/tests.log | head
timeout 60 python3 -m benchmarks.recon_ssim --device cuda --sizes 270x480,540x960,1080x1920 > $OUT/ssim.txt 2>&1; cat $OUT/ssim.txt
echo "train $(date -u +%T)"; timeout 200 python3 -m benchmarks.gpu.train_vs_gsplat --data .carry/realscene/fox --steps 30 --warmup 6 --json $OUT/train_vs_gsplat.json > $OUT/train.txt 2>&1; echo "train rc=$?"; grep -A8 "^== Training" $OUT/train.txt; grep -A12 "'variant': 'ours (again)'" $OUT/train.txt
echo "guidance $(date -u +%T)"; timeout 230 python3 -m benchmarks.guidance --device cuda --dtypes bf16 --modes graph,eager --budget-s 150 --out $OUT/guidance.json 2>&1 | grep -v -i -e warn -e "Model config" > $OUT/guidance.txt; tail -22 $OUT/guidance.txt; echo "end $(date -u +%T)"
