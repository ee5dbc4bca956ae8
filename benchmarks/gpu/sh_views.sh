#!/usr/bin/env bash
# One device call for the SH op over V views (sh_to_color with dirs [V, N, 3]; first run on the H100 in
# the round that added it): build, the SH and render_views tests (their CUDA cases are marked cuda),
# compute-sanitizer memcheck and racecheck on the SH kernels (plain and staged, one and several
# views), then benchmarks/sh_views.py (V one-view calls against one V-view call) and the edit's
# render stage. From the repo root with .carry/deb carried; results also under $OUT/sh_views.
cd "$(dirname "$0")/../.."
export OUT="${OUT:-outputs}" PYTHONUNBUFFERED=1
mkdir -p "$OUT/sh_views"
CHECK_STEPS=build OUT="$OUT/sh_views" bash benchmarks/gpu/check.sh "" .carry/deb/libeigen3-dev_3.4.0-4_all.deb >/dev/null 2>&1
tail -1 "$OUT/sh_views/check.log"
timeout 300 python3 -m pytest -q -p no:cacheprovider tests/ops/test_sh_views.py tests/ops/test_sh.py \
  tests/ops/test_sh_trainable.py tests/scene/test_render_views.py > "$OUT/sh_views/tests.log" 2>&1
echo "tests rc=$?: $(tail -1 "$OUT/sh_views/tests.log")"; grep -E "^(FAILED|ERROR)" "$OUT/sh_views/tests.log" | head -20
SAN="$(command -v compute-sanitizer || echo /usr/local/cuda/bin/compute-sanitizer)"
for tool in memcheck racecheck; do
  PYTORCH_NO_CUDA_MEMORY_CACHING=1 timeout 150 "$SAN" --tool $tool --error-exitcode 99 --kernel-name kns=sh_ \
    python3 -m pytest -q -p no:cacheprovider tests/ops/test_sh_views.py -k cuda > "$OUT/sh_views/$tool.log" 2>&1
  echo "$tool rc=$?: $(grep -E 'ERROR SUMMARY|RACECHECK SUMMARY' "$OUT/sh_views/$tool.log" | tail -1)"
done
timeout 120 python3 -m benchmarks.sh_views --device cuda --views 4 8 2>&1 | tee "$OUT/sh_views/bench.txt"
timeout 240 python3 -m benchmarks.render_views --edit --density 16 --size 512 --views 8 --device cuda \
  > "$OUT/sh_views/render_views.txt" 2>&1
echo "render_views --edit rc=$?"; tail -25 "$OUT/sh_views/render_views.txt"
