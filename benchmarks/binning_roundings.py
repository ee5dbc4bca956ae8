"""How much the float32 rounding of the binning's tile test decides (the heavy-tailed scene).

Before the tile test spelled out its multiply-adds as fma, nvcc rounded it in two ways: the
one-thread-per-Gaussian kernel as fma(fma(a, t, 2b), t, c) where it hoisted terms out of the
tile loop, the chunked kernel as fma(x, k x, t (a t + 2b)) ("chunked_v2"). This counts the
(tile, Gaussian) decisions of the Gaussians with more than 32 candidate tiles (those the
balanced CUDA path bins apart) that differ between the two roundings, on the CPU, with the
float32 emulation of tests/render/tile_test_f32.py. Usage: python -m benchmarks.binning_roundings
[--n 1000000] (about a minute for 1e6 Gaussians at 1920x1080).
"""
from __future__ import annotations

import argparse
import math
import time

import numpy as np
import torch

from tests.render.standard_scenes import heavy_tailed_scene, standard_camera  # noqa: E402
from tests.render.tile_test_f32 import tile_pairs  # noqa: E402

import tiger  # noqa: E402,F401

TS, THR = 16, 1 / 255


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--n", type=int, default=1_000_000)
    p.add_argument("--width", type=int, default=1920)
    p.add_argument("--height", type=int, default=1080)
    args = p.parse_args()
    w, h = args.width, args.height
    s = heavy_tailed_scene(args.n, 3)
    V, K = standard_camera(w, h)
    m2, cn, d, op, r = [t.numpy() for t in torch.ops.tiger.project_gaussians(
        s["means"], s["quats"], s["scales"], s["opacities"], V, K, w, h, 0.3, 0.01, 1e10, THR, False)]
    tx, ty = math.ceil(w / TS), math.ceil(h / TS)
    u, v = m2[:, 0].astype(np.float64), m2[:, 1].astype(np.float64)
    bx = np.clip(np.floor((u + r[:, 0]) / TS) + 1, 0, tx) - np.clip(np.floor((u - r[:, 0]) / TS), 0, tx)
    by = np.clip(np.floor((v + r[:, 1]) / TS) + 1, 0, ty) - np.clip(np.floor((v - r[:, 1]) / TS), 0, ty)
    cand = np.where((r[:, 0] > 0) & (r[:, 1] > 0), np.maximum(bx, 0) * np.maximum(by, 0), 0)
    large = np.nonzero(cand > 32)[0]
    print(f"heavy scene n={args.n} {w}x{h}: {len(large)} Gaussians with > 32 candidate tiles, "
          f"{int(cand[large].sum())} candidates (all: {int(cand.sum())})", flush=True)
    t0 = time.time()
    differ, ends, start = [], np.cumsum(cand[large]), 0
    while start < len(large):
        stop = max(start + 1, int(np.searchsorted(ends, (ends[start - 1] if start else 0) + 3_000_000)))
        rr = np.zeros_like(r)
        rr[large[start:stop]] = r[large[start:stop]]
        a = tile_pairs(m2, cn, op, rr, w, h, TS, THR, "fused")
        b = tile_pairs(m2, cn, op, rr, w, h, TS, THR, "chunked_v2")
        differ.extend(np.setxor1d(a, b).tolist())
        start = stop
    print(f"{time.time() - t0:.0f} s: {len(differ)} decisions differ between the two roundings")
    n = len(r)
    for key in differ:
        g, tile = key % n, key // n
        print(f"  Gaussian {g}: tile {tile}, {int(cand[g])} candidate tiles, opacity {op[g]:.4g}")


if __name__ == "__main__":
    main()
