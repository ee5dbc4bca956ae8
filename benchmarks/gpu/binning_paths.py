"""The CUDA binning's two paths against each other over scene size.

``tiger.bin_gaussians`` sorts each tile's list on its own (per-tile path) for scenes of up to
``kBinTilePathMaxGaussians`` Gaussians, and by a depth sort plus a device-wide stable radix sort
by tile (global path) beyond (csrc/binning/binning_cuda.h). This script times the op with each
path forced (the op's ``path`` argument), median of CUDA events, on the standard and the heavy-tailed
synthetic scenes at 1920x1080 for several N, and checks that both give identical lists.

    python -m benchmarks.gpu.binning_paths --n 50000,100000,200000,400000,1000000
"""
from __future__ import annotations

import argparse

import torch

from benchmarks.common import cuda_time_ms  # noqa: E402
from tests.render.standard_scenes import heavy_tailed_scene, standard_camera, standard_scene  # noqa: E402
from benchmarks.gpu.real_scenes import project  # noqa: E402

import tiger  # noqa: E402,F401  (registers the ops)


def bin_with_path(path: str, proj, w: int, h: int):
    m2, cn, d, op, r = proj
    return torch.ops.tiger.bin_gaussians(m2, cn, op, d, r, w, h, 16, 1 / 255, path)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--n", default="50000,100000,200000,400000,1000000")
    p.add_argument("--iters", type=int, default=30)
    args = p.parse_args()
    w, h = 1920, 1080
    V, K = standard_camera(w, h, device="cuda")
    print(f"{'scene':9s} {'N':>8s} {'isects':>9s} {'tiles ms':>9s} {'global ms':>9s} {'ratio':>6s} same")
    for name, make in (("standard", standard_scene), ("heavy", heavy_tailed_scene)):
        for n in (int(x) for x in args.n.split(",")):
            scene = make(n, 3, device="cuda")
            proj = project(scene, V, K, w, h)
            ms = {path: cuda_time_ms(lambda: bin_with_path(path, proj, w, h), iters=args.iters)
                  for path in ("tiles", "global")}
            a, b = bin_with_path("tiles", proj, w, h), bin_with_path("global", proj, w, h)
            same = bool(torch.equal(a[0], b[0]) and torch.equal(a[1], b[1]))
            print(f"{name:9s} {n:8d} {a[1].numel():9d} {ms['tiles']:9.3f} {ms['global']:9.3f} "
                  f"{ms['tiles'] / ms['global']:6.2f} {same}", flush=True)


if __name__ == "__main__":
    main()
