#!/usr/bin/env bash
# Fill (here, where PyPI and Debian are reachable) what the device scripts expect to be carried:
#   .whl/           diffusers, transformers, safetensors and their pure needs (the edit benchmarks)
#   .carry/whl_gs/  gsplat 1.5.3 and its needs (the comparisons; it JIT-compiles on first use, ~80 s
#                   on the H100: pack TORCH_EXTENSIONS_DIR into .carry/gsplat_ext.tgz to reuse it)
#   .carry/deb/     Eigen's .deb (the build, where the device image lacks Eigen)
# CPython 3.12, x86-64. torch, numpy and the CUDA wheels stay the device image's own. The real
# scenes are not fetched here: .carry/realscene/fox is shared/data/fox, and snowmiku's
# points3D.bin, cameras.bin and cameras.json come from github.com/noname0310/snowmiku2023plush-splat.
# Usage, from the repo root: bash benchmarks/gpu/carry_wheels.sh   (then carry the three folders;
# the device's file limit is 64 MiB in all with the tree).
set -euo pipefail
download() {  # DIR PACKAGE...
  local dir=$1; shift
  mkdir -p "$dir"
  python3 -m pip download -q --only-binary=:all: --python-version 3.12 --implementation cp \
    --platform manylinux_2_28_x86_64 --platform manylinux_2_17_x86_64 --platform manylinux2014_x86_64 \
    --platform any -d "$dir" "$@"
  (cd "$dir" && rm -f torch-* nvidia_* triton-* numpy-* sympy-* mpmath-* networkx-* jinja2-* \
    markupsafe-* typing_extensions-* packaging-* pillow-* setuptools-*)
}
download .whl "diffusers==0.42.*" "transformers>=4.40" safetensors
download .carry/whl_gs gsplat==1.5.3 ninja
mkdir -p .carry/deb && (cd .carry/deb && apt-get download libeigen3-dev)
du -sh .whl .carry/whl_gs .carry/deb
