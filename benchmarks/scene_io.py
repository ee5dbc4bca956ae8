"""Scene I/O stages: PLY write/read, COLMAP parsing, image undistortion -- run time
against error (round-trip exactness; float32 vs float64 undistortion).

    python -m benchmarks.scene_io [--quick]
"""
from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

from tests.scene.colmapref import write_model  # noqa: E402  (the tests' independent writer)

from tiger.render import Distortion  # noqa: E402
from tiger.scene import GaussianScene  # noqa: E402
from tiger.scene.cameras import intrinsics  # noqa: E402
from tiger.scene.colmap import read_model  # noqa: E402
from tiger.scene.images import distort_points, undistort_image, undistort_points  # noqa: E402


def bench_ply(sizes: list) -> None:
    print("\n### PLY (INRIA layout, SH degree 3, float32)")
    print("| Gaussians | file MB | write s | read s | read MB/s | round trip |")
    print("|---:|---:|---:|---:|---:|---|")
    for n in sizes:
        g = torch.Generator().manual_seed(0)
        s = GaussianScene(*(torch.randn(*shape, generator=g) for shape in
                            [(n, 3), (n, 3), (n, 4), (n,), (n, 3), (n, 15, 3)]))
        with tempfile.TemporaryDirectory() as d:
            p = Path(d) / "s.ply"
            t0 = time.perf_counter()
            s.save_ply(p)
            tw = time.perf_counter() - t0
            t0 = time.perf_counter()
            r = GaussianScene.load_ply(p)
            tr = time.perf_counter() - t0
            mb = p.stat().st_size / 1e6
        print(f"| {n} | {mb:.1f} | {tw:.3f} | {tr:.3f} | {mb / tr:.0f} | {'bit-exact' if r.equal(s) else 'MISMATCH'} |")


def bench_colmap(points: list) -> None:
    print("\n### COLMAP sparse model (100 images x 500 2D points, P 3D points with 4-view tracks)")
    print("| points3D | binary s | text s | text == binary |")
    print("|---:|---:|---:|---|")
    rng = np.random.default_rng(0)
    cams = [(1, "OPENCV", 1920, 1080, (1500.0, 1500.0, 960.0, 540.0, 0.01, -0.02, 1e-4, 1e-4))]
    imgs = [(i + 1, tuple(rng.normal(size=4) / 2), tuple(rng.normal(size=3)), 1, f"im{i:04d}.jpg",
             [(float(x), float(y), -1) for x, y in rng.uniform(0, 1000, (500, 2))]) for i in range(100)]
    for p in points:
        pts = [(j, tuple(rng.normal(size=3)), (1, 2, 3), 0.5, [(1, j), (2, j), (3, j), (4, j)]) for j in range(p)]
        with tempfile.TemporaryDirectory() as d:
            times = {}
            out = {}
            for binary in (True, False):
                folder = Path(d) / ("b" if binary else "t")
                write_model(folder, cams, imgs, pts, binary)
                t0 = time.perf_counter()
                out[binary] = read_model(folder)
                times[binary] = time.perf_counter() - t0
            same = (out[True][0] == out[False][0] and out[True][1] == out[False][1]
                    and np.array_equal(out[True][2].xyz, out[False][2].xyz))
        print(f"| {p} | {times[True]:.3f} | {times[False]:.3f} | {same} |")


def bench_undistort(sizes: list) -> None:
    d = Distortion(k1=0.0578421, k2=-0.0805099, p1=-0.000980296, p2=0.00015575)   # the fox lens
    print("\n### Undistortion (fox lens), float32 sampling vs float64 reference, image values in [0, 1]")
    print("| W x H | undistort s | max abs err | mean abs err |")
    print("|---|---:|---:|---:|")
    for W, H in sizes:
        K = intrinsics(1.27 * W, 1.27 * W, W / 2, H / 2)
        img = torch.rand(H, W, 3, generator=torch.Generator().manual_seed(0))
        img = F.avg_pool2d(img.permute(2, 0, 1)[None], 3, 1, 1)[0].permute(1, 2, 0)   # not pure noise
        t0 = time.perf_counter()
        out = undistort_image(img, K, d)
        t = time.perf_counter() - t0
        # float64 reference: same mapping, float64 sampling
        v, u = torch.meshgrid(torch.arange(H, dtype=torch.float64) + 0.5, torch.arange(W, dtype=torch.float64) + 0.5,
                              indexing="ij")
        xy = torch.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1]], -1)
        xyd = distort_points(xy, d)
        grid = torch.stack([(xyd[..., 0] * K[0, 0] + K[0, 2]) / W * 2 - 1,
                            (xyd[..., 1] * K[1, 1] + K[1, 2]) / H * 2 - 1], -1)[None]
        ref = F.grid_sample(img.double().permute(2, 0, 1)[None], grid, align_corners=False)[0].permute(1, 2, 0)
        err = (out.double() - ref).abs()
        print(f"| {W} x {H} | {t:.3f} | {float(err.max()):.1e} | {float(err.mean()):.1e} |")
    print("\n### undistort_points (Newton) convergence: max |distort(undistort(p)) - p| (normalised coords)")
    print("| iterations | float64 error |")
    print("|---:|---:|")
    p = torch.rand(10000, 2, dtype=torch.float64) * 1.2 - 0.6
    for it in (1, 2, 3, 5, 10, 30):
        e = float((distort_points(undistort_points(p, d, iters=it), d) - p).abs().max())
        print(f"| {it} | {e:.1e} |")


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--quick", action="store_true")
    args = ap.parse_args()
    bench_ply([10_000, 100_000] if args.quick else [10_000, 100_000, 1_000_000])
    bench_colmap([1000, 10_000] if args.quick else [1000, 10_000, 100_000])
    bench_undistort([(270, 480), (1080, 1920)] if args.quick else [(270, 480), (540, 960), (1080, 1920)])


if __name__ == "__main__":
    main()
