"""An independent float32 emulation of the binning's tile test (numpy, one IEEE rounding per
operation), for tests that pin the exact arithmetic of ``csrc/common/raster_math.h``:

    q_edge = fma(fma(a, t, 2 b), t, c),  t = clamp(-b / a, lo, hi),  c = (k x) x
    qcut   = fma(2 log(o / thr), 1.0001, 1e-4)

A compiler that fuses a * b + c on its own rounds some of these terms differently depending
on the code around them; near qcut that flips tiles in or out of the lists (the CUDA
one-thread-per-Gaussian and chunked binnings disagreed on the heavy scene that way).
``variant`` selects the roundings to emulate: "fused" (the specification above), "plain" (no
fma at all) or "chunked_v2" (what nvcc made of the chunked CUDA kernel before the fix:
fma(x, k x, t (a t + 2 b))).
"""
from __future__ import annotations

import math

import numpy as np

F32, F64 = np.float32, np.float64


def fma32(a, b, c) -> np.ndarray:
    """float32 a * b + c with a single rounding (round to nearest even), elementwise.

    The float64 sum p + c of the exact product p = a b is rounded once more to float32; that
    second rounding is wrong only where the float64 sum lies exactly halfway between two
    float32 numbers and is itself inexact, which the error term of TwoSum corrects."""
    a, b, c = np.broadcast_arrays(np.asarray(a, F32), np.asarray(b, F32), np.asarray(c, F32))
    p = a.astype(F64) * b.astype(F64)  # exact: 24 + 24 bits
    cd = c.astype(F64)
    s = p + cd
    bp = s - p
    err = (p - (s - bp)) + (cd - bp)  # s + err == p + c exactly
    r = s.astype(F32)
    rd = r.astype(F64)
    other = np.nextafter(r, np.where(s > rd, np.inf, -np.inf).astype(F32))
    tie = (rd != s) & ((rd + other.astype(F64)) * 0.5 == s) & (err != 0)
    pick_other = tie & (np.sign(err) == np.sign(other.astype(F64) - s))
    return np.where(pick_other, other, r)


def _segment_min(a, b, k, x, lo, hi, variant: str) -> np.ndarray:
    """min over t in [lo, hi] of a t^2 + 2 b t + k x^2 (float32 arrays)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.where(a > 0, -b / a, lo)
    t = np.where(t < lo, lo, np.where(t > hi, hi, t))
    kx = k * x
    if variant == "fused":
        return fma32(fma32(a, t, F32(2) * b), t, kx * x)
    if variant == "chunked_v2":
        return fma32(x, kx, t * (a * t + F32(2) * b))
    if variant == "plain":
        return (a * t + F32(2) * b) * t + kx * x
    raise ValueError(f"unknown variant {variant!r}")


def min_quadratic_on_rect(ca, cb, cc, x0, x1, y0, y1, variant: str = "fused") -> np.ndarray:
    """min of d^T [[ca, cb], [cb, cc]] d over the offsets [x0, x1] x [y0, y1] (float32)."""
    m = _segment_min(cc, cb * x0, ca, x0, y0, y1, variant)
    for e in (_segment_min(cc, cb * x1, ca, x1, y0, y1, variant),
              _segment_min(ca, cb * y0, cc, y0, x0, x1, variant),
              _segment_min(ca, cb * y1, cc, y1, x0, x1, variant)):
        m = np.where(e < m, e, m)
    inside = (x0 <= 0) & (0 <= x1) & (y0 <= 0) & (0 <= y1)
    return np.where(inside, F32(0), m)


def cutoff_quadratic(opacities, threshold: float, variant: str = "fused") -> np.ndarray:
    """qcut per Gaussian; the log is float64's rounded to float32 (glibc's logf is within
    about half an ulp: exact for the ratio 1 the crafted cases use)."""
    with np.errstate(divide="ignore", invalid="ignore"):  # culled rows may hold opacity 0
        k2 = F32(2) * np.log((np.asarray(opacities, F32) / F32(threshold)).astype(F64)).astype(F32)
        if variant != "fused":
            return k2 * F32(1.0001) + F32(1e-4)
        return fma32(k2, F32(1.0001), F32(1e-4))


def tile_pairs(means2d, conics, opacities, radii, width: int, height: int, tile_size: int,
               threshold: float, variant: str = "fused") -> np.ndarray:
    """Sorted keys tile * N + gaussian of every listed (tile, Gaussian) pair: the candidate
    tiles of the bounding box (float64, as tile_rect) that pass the float32 tile test."""
    m2, cn = np.asarray(means2d, F32), np.asarray(conics, F32)
    r = np.asarray(radii).astype(np.int64)
    n = len(r)
    tx, ty = math.ceil(width / tile_size), math.ceil(height / tile_size)
    vis = np.nonzero((r[:, 0] > 0) & (r[:, 1] > 0))[0]
    u, v = m2[vis, 0], m2[vis, 1]
    rx, ry = r[vis, 0].astype(F64), r[vis, 1].astype(F64)
    clamp = lambda a, hi: np.clip(a, 0, hi).astype(np.int64)  # noqa: E731
    bx0 = clamp(np.floor((u.astype(F64) - rx) / tile_size), tx)
    bx1 = clamp(np.floor((u.astype(F64) + rx) / tile_size) + 1, tx)
    by0 = clamp(np.floor((v.astype(F64) - ry) / tile_size), ty)
    by1 = clamp(np.floor((v.astype(F64) + ry) / tile_size) + 1, ty)
    bw = np.maximum(bx1 - bx0, 0)
    count = bw * np.maximum(by1 - by0, 0)
    g = np.repeat(np.arange(len(vis)), count)
    j = np.arange(int(count.sum())) - np.repeat(np.cumsum(count) - count, count)
    gx, gy = bx0[g] + j % np.maximum(bw[g], 1), by0[g] + j // np.maximum(bw[g], 1)
    px0, py0 = gx * tile_size, gy * tile_size
    px1, py1 = np.minimum(px0 + tile_size, width), np.minimum(py0 + tile_size, height)
    x0 = (px0.astype(F32) + F32(0.5)) - u[g]
    x1 = (px1.astype(F32) - F32(0.5)) - u[g]
    y0 = (py0.astype(F32) + F32(0.5)) - v[g]
    y1 = (py1.astype(F32) - F32(0.5)) - v[g]
    q = min_quadratic_on_rect(cn[vis, 0][g], cn[vis, 1][g], cn[vis, 2][g], x0, x1, y0, y1, variant)
    qcut = cutoff_quadratic(np.asarray(opacities)[vis], threshold, variant)[g]
    keep = q <= qcut
    return np.sort((gy * tx + gx)[keep] * n + vis[g][keep])


def borderline_gaussians(n: int, tile_size: int, tiles: int, threshold: float, seed: int = 0):
    """n float32 Gaussians on a ``tiles`` x ``tiles`` grid whose ellipse edge q = qcut passes
    within rounding error of a tile's nearest pixel centres, with strong cancellation (thin,
    tilted ellipses): the cases where the roundings of the tile test decide.

    Opacity equals the threshold, so qcut = fma(0, 1.0001, 1e-4) = 1e-4 exactly (no log).
    The minimum of q along a tile's vertical edge at offset x is x^2 det / c; x is set so that
    it equals qcut up to a relative jitter of 1e-3. Radii cover the whole grid (tiles^2
    candidate tiles each). Returns means2d [n, 2], conics [n, 3], opacities [n], depths [n],
    radii [n, 2] int32 (numpy)."""
    rng = np.random.default_rng(seed)
    size = tiles * tile_size
    L = rng.uniform(200.0, 2000.0, n)
    kappa = L * 10.0 ** rng.uniform(-4.5, -3.0, n)  # det / c: the cancellation is L / kappa
    a = c = L
    b = np.sqrt(L * L - kappa * L) * rng.choice([-1.0, 1.0], n)
    x = np.sqrt(1e-4 / kappa) * (1.0 + 1e-3 * rng.uniform(-1.0, 1.0, n))
    # Edge of a tile in the middle of the grid; the mean sits x to its left and high enough
    # that the edge's minimum (t = -b x / c) falls inside the tile's pixel-centre range.
    tile_x = rng.integers(1, tiles - 1, n)
    tile_y = rng.integers(1, tiles - 1, n)
    u = tile_x * tile_size + 0.5 - x
    v = tile_y * tile_size + tile_size / 2 + np.sign(b) * x
    means2d = np.stack([u, v], 1).astype(F32)
    conics = np.stack([a, b, c], 1).astype(F32)
    opacities = np.full(n, threshold, F32)
    depths = rng.uniform(1.0, 2.0, n).astype(F32)
    radii = np.full((n, 2), size, np.int32)
    return means2d, conics, opacities, depths, radii
