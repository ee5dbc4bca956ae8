"""Inputs shared by the rendering-op tests: a small projected scene and its tile lists."""
from __future__ import annotations

import torch

import tiger  # noqa: F401  (registers the ops)

from ..render.scenes import camera, random_scene

F64 = torch.float64
ops = torch.ops.tiger


def _projection_args(n=6, w=24, h=20, seed=0, dtype=F64, device="cpu"):
    m, q, s, o, _ = random_scene(n, 1, dtype=dtype, seed=seed, scale_range=(0.1, 0.4),
                                 opacity_range=(0.3, 0.9))
    V, K = camera(w, h, dtype=dtype)
    return (*[t.to(device) for t in (m, q, s, o, V, K)], w, h)


def _raster_args(n=8, c=4, w=20, h=18, seed=0, dtype=F64, device="cpu"):
    m, q, s, o, V, K, w, h = _projection_args(n, w, h, seed, dtype, device)
    m2, cn, d, op, r = ops.project_gaussians(m, q, s, o, V, K, w, h, 0.3, 0.01, 1e10, 1 / 255, False)
    col = torch.rand(n, c, dtype=dtype, generator=torch.Generator().manual_seed(seed)).to(device)
    bg = torch.rand(c, dtype=dtype, generator=torch.Generator().manual_seed(seed + 1)).to(device)
    to, ids = ops.bin_gaussians(m2, cn, op, d, r, w, h, 16, 1 / 255)
    return m2, cn, op, col, d, bg, to, ids, w, h
