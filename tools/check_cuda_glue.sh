#!/usr/bin/env bash
# Syntax-check the torch glue of the CUDA kernels (*_cuda.cpp) with the host compiler
# against the installed torch headers and the CUDA include dir; no GPU and no CUDA torch
# needed. Run from the repo root with PY pointing at the project's python.
set -euo pipefail
cd "$(dirname "$0")/.."
PY="${PY:-.venv/bin/python}"
NVCC="${NVCC:-$(command -v nvcc || true)}"
[ -n "$NVCC" ] || { echo "nvcc not found: skipping the CUDA glue check"; exit 0; }
CUDA_INC=""
for d in "${CUDA_HOME:-}" "$(dirname "$(dirname "$(readlink -f "$NVCC")")")" /usr/local/cuda /usr/local/cuda-*; do
  [ -n "$d" ] && [ -f "$d/include/cuda_runtime_api.h" ] && { CUDA_INC="$d/include"; break; }
done
[ -n "$CUDA_INC" ] || { echo "CUDA headers not found: skipping the CUDA glue check"; exit 0; }
TORCH_INC="$("$PY" -c 'import torch.utils.cpp_extension as c; print(" ".join("-I"+p for p in c.include_paths()))')"
PYINC="$("$PY" -c 'import sysconfig; print(sysconfig.get_paths()["include"])')"
# A CPU torch wheel lacks this one generated header of its CUDA build: stand it in.
stub=$(mktemp -d); trap 'rm -rf "$stub"' EXIT
mkdir -p "$stub/c10/cuda/impl"
echo '#define C10_CUDA_BUILD_SHARED_LIBS' > "$stub/c10/cuda/impl/cuda_cmake_macros.h"
mapfile -t files < <(find csrc -name '*_cuda.cpp' | sort)
echo "glue syntax check: ${#files[@]} files"
status=0
for f in "${files[@]}"; do
  if ! ${CXX:-g++} -std=c++17 -fsyntax-only -Wno-c++20-extensions -DTIGER_WITH_CUDA=1 -Icsrc -I"$CUDA_INC" -I"$PYINC" $TORCH_INC -I"$stub" "$f"; then
    echo "FAILED: $f" >&2; status=1
  fi
done
exit $status
