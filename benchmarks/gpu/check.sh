#!/usr/bin/env bash
# GPU check of the CUDA rendering core, in one call on a machine with one GPU:
#   1. build tiger with CUDA (pip install --no-build-isolation --no-deps -e .)
#   2. the test suite on CUDA (CUDA vs CPU vs float64 reference, gradcheck in float64)
#   3. compute-sanitizer memcheck (all kernels) and racecheck (rasterizer) on a small case
#   4. the benchmark against gsplat 1.5.3 (if its wheel is given) and the error sweep
# Results go under $OUT (check.log, tests.log, sanitizer.log, bench.txt, bench.json).
# Usage, from the repo root:  OUT=/tmp/out bash benchmarks/gpu/check.sh [WHEEL_DIR] [EIGEN_DEB]
# Environment: CHECK_STEPS (default "build tests sanitizer bench"), BENCH_ARGS, PYTEST_ARGS;
#   TEST_WHEELS: a folder of wheels for the tests only (nbformat, nbclient, ipykernel and their
#   needs: benchmarks/gpu/test_wheels.sh downloads them), so the notebook tests run;
#   TEST_DATA: the shared data folder (the fox capture), linked as ../shared/data beside the repo
#   when that is missing, so the real-data tests run.
set -uo pipefail
cd "$(dirname "$0")/../.."
OUT="${OUT:-/tmp/tiger-gpu-check}"
mkdir -p "$OUT"
WHEELS="${1:-}"
EIGEN_DEB="${2:-}"
STEPS="${CHECK_STEPS:-build nocuda tests sanitizer bench}"
PY="${PYTHON:-python3}"
export PYTHONUNBUFFERED=1
LOG="$OUT/check.log"
status=0
say() { echo "[$(date -u +%H:%M:%S)] $*" | tee -a "$LOG"; }
has() { [[ " $STEPS " == *" $1 "* ]]; }

say "GPU: $(nvidia-smi --query-gpu=name,driver_version,memory.total --format=csv,noheader 2>&1)"
say "python: $($PY -c 'import sys, torch; print(sys.version.split()[0], torch.__version__, torch.version.cuda)')"
say "nvcc: $(nvcc --version | tail -1)"

if [ -n "$WHEELS" ] && ls "$WHEELS"/*.whl >/dev/null 2>&1; then
  $PY -m pip install -q --no-index --no-deps --no-compile --target /tmp/site "$WHEELS"/*.whl \
    && export PYTHONPATH="/tmp/site${PYTHONPATH:+:$PYTHONPATH}"
  say "wheels installed: $(ls "$WHEELS")"
fi

if [ -n "${TEST_WHEELS:-}" ] && ls "$TEST_WHEELS"/*.whl >/dev/null 2>&1; then
  $PY -m pip install -q --no-index --no-deps --no-compile --target /tmp/site "$TEST_WHEELS"/*.whl \
    && export PYTHONPATH="/tmp/site${PYTHONPATH:+:$PYTHONPATH}"
  say "test wheels installed: $(ls "$TEST_WHEELS" | wc -l) ($($PY -c 'import nbformat, nbclient, ipykernel; print("nbformat", nbformat.__version__)' 2>&1 | tail -1))"
fi
if [ -n "${TEST_DATA:-}" ] && [ ! -e ../shared/data ]; then
  mkdir -p ../shared && ln -s "$(cd "$TEST_DATA" && pwd)" ../shared/data
  say "test data: ../shared/data -> $TEST_DATA ($(ls ../shared/data | tr '\n' ' '))"
fi

if has build; then
  CMAKE_EXTRA=()
  if ! [ -f /usr/include/eigen3/Eigen/Core ] && [ -n "$EIGEN_DEB" ]; then
    dpkg -x "$EIGEN_DEB" /tmp/eigen
    CMAKE_EXTRA+=(--config-settings=cmake.define.Eigen3_DIR=/tmp/eigen/usr/share/eigen3/cmake)
  fi
  # The device image presets CXX=/opt/gcc/bin/g++, whose modules carry a private copy of
  # libstdc++ (no libstdc++.so in ldd): any C++ error message that formats an integer then
  # segfaults inside torch's process. The system g++ builds a normal module.
  if [ -z "${TIGER_KEEP_CXX:-}" ] && [ -x /usr/bin/g++ ]; then
    export CXX=/usr/bin/g++ CUDAHOSTCXX=/usr/bin/g++ CC=/usr/bin/gcc
    CMAKE_EXTRA+=(--config-settings=build-dir=build/system-gxx)
  fi
  say "build (CUDA arch ${TIGER_CHECK_ARCHS:-90}, CXX=${CXX:-default})"
  t0=$(date +%s)
  if ! CMAKE_BUILD_PARALLEL_LEVEL=$(nproc) $PY -m pip install --no-build-isolation --no-deps -e . \
      --config-settings=cmake.define.CMAKE_CUDA_ARCHITECTURES="${TIGER_CHECK_ARCHS:-90}" \
      "${CMAKE_EXTRA[@]}" > "$OUT/build.log" 2>&1; then
    say "BUILD FAILED"; tail -60 "$OUT/build.log" | tee -a "$LOG"; exit 1
  fi
  say "build ok in $(( $(date +%s) - t0 )) s; cuda_enabled=$($PY -c 'import tiger.ops as o; print(o.cuda_enabled())'); $(ldd "$($PY -c 'import tiger._C as c; print(c.__file__)')" | grep -o 'libstdc++[^ ]*' | head -1)"
fi

if has nocuda; then
  # TIGER_CUDA=0 must switch the CUDA build off even where torch has CUDA and nvcc exists.
  rm -rf /tmp/tiger-nocuda
  EIGEN_DIR_ARG=()
  [ -d /tmp/eigen ] && EIGEN_DIR_ARG=(-DEigen3_DIR=/tmp/eigen/usr/share/eigen3/cmake)
  TIGER_CUDA=0 cmake -S . -B /tmp/tiger-nocuda -G Ninja -DPython_EXECUTABLE="$(command -v $PY)" \
    "${EIGEN_DIR_ARG[@]}" > "$OUT/nocuda.log" 2>&1
  rc=$?
  flag=$(grep -E '^TIGER_CUDA:BOOL' /tmp/tiger-nocuda/CMakeCache.txt 2>/dev/null)
  [ $rc -eq 0 ] && [ "$flag" = "TIGER_CUDA:BOOL=OFF" ] || status=1
  say "TIGER_CUDA=0 configure rc=$rc: $flag"
fi

if has tests; then
  say "test suite (${TEST_MARKERS:-not slow}; the CUDA tests are those marked cuda)"
  $PY -m pytest -q -m "${TEST_MARKERS:-not slow}" -p no:cacheprovider --timeout 600 ${PYTEST_ARGS:-} tests > "$OUT/tests.log" 2>&1
  rc=$?; [ $rc -ne 0 ] && status=1
  say "tests rc=$rc: $(tail -1 "$OUT/tests.log")"
  grep -E "^(FAILED|ERROR)" "$OUT/tests.log" | head -30 | tee -a "$LOG"
fi

if has sanitizer; then
  SAN="$(command -v compute-sanitizer || echo /usr/local/cuda/bin/compute-sanitizer)"
  say "compute-sanitizer memcheck (every kernel, caching allocator off)"
  PYTORCH_NO_CUDA_MEMORY_CACHING=1 timeout "${SANITIZER_TIMEOUT:-300}" "$SAN" --tool memcheck --error-exitcode 99 \
    $PY -m benchmarks.gpu.sanitize_case > "$OUT/sanitizer.log" 2>&1
  rc=$?; [ $rc -ne 0 ] && status=1
  say "memcheck rc=$rc: $(grep -E 'ERROR SUMMARY' "$OUT/sanitizer.log" | tail -1)"
  say "compute-sanitizer racecheck (rasterizer kernels)"
  timeout "${SANITIZER_TIMEOUT:-300}" "$SAN" --tool racecheck --error-exitcode 99 --kernel-name kns=raster_cuda \
    $PY -m benchmarks.gpu.sanitize_case >> "$OUT/sanitizer.log" 2>&1
  rc=$?; [ $rc -ne 0 ] && status=1
  say "racecheck rc=$rc: $(grep -E 'RACECHECK SUMMARY|ERROR SUMMARY' "$OUT/sanitizer.log" | tail -1)"
fi

if has bench; then
  say "benchmark (gsplat JIT-compiles on first use)"
  export MAX_JOBS="${MAX_JOBS:-$(nproc)}" TORCH_CUDA_ARCH_LIST="${TORCH_CUDA_ARCH_LIST:-9.0}"
  timeout "${BENCH_TIMEOUT:-900}" $PY -m benchmarks.gpu.rasterize_vs_gsplat --json "$OUT/bench.json" --profile "$OUT/profile.txt" ${BENCH_ARGS:-} \
    > "$OUT/bench.txt" 2>&1
  rc=$?; [ $rc -ne 0 ] && status=1
  say "benchmark rc=$rc"
  sed -n '/^== /,$p' "$OUT/bench.txt" | tee -a "$LOG"
  [ $rc -ne 0 ] && tail -30 "$OUT/bench.txt" | tee -a "$LOG"
fi
say "done, status=$status"
exit $status
