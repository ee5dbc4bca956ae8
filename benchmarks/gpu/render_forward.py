"""The no-gradient forward in one op (``tiger::render_forward``, what ``rasterize_gaussians`` runs
when nothing records gradients) against the op-by-op render it replaced (``project_for_raster`` +
``composite``): wall time by CUDA events, both in one process, interleaved (4 x 30 forwards each),
and whether the outputs are identical. Cases: snowmiku at 1080p (the COLMAP points of
``.carry/realscene/snowmiku``) and the standard 200k-Gaussian scene at 1920x1080.
Usage: python -m benchmarks.gpu.render_forward [--snowmiku PATH]"""
from __future__ import annotations

import argparse
from pathlib import Path

import torch

import tiger
from benchmarks.common import cuda_time_ms
from benchmarks.gpu.real_scenes import snowmiku
from tests.render.standard_scenes import standard_camera, standard_scene
from tiger.render.rasterize import RasterSettings, composite, project_for_raster


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--snowmiku", type=Path, default=Path(".carry/realscene/snowmiku"))
    p.add_argument("--rounds", type=int, default=4)
    args = p.parse_args()
    cases = {}
    if args.snowmiku.is_dir():
        cases["snowmiku-1080p"] = snowmiku(args.snowmiku, 1080, "cuda")
    sc = standard_scene(200_000, 3, device="cuda")
    V, K = standard_camera(1920, 1080, device="cuda")
    cases["standard200k-1080p"] = ({k: v.contiguous() for k, v in sc.items()}, V, K, 1920, 1080)
    settings = RasterSettings(check_finite=False)
    print(f"# python -m benchmarks.gpu.render_forward, {torch.cuda.get_device_name()}")
    with torch.no_grad():
        for name, (s, V, K, w, h) in cases.items():
            a = (s["means"], s["quats"], s["scales"], s["opacities"], s["colors"], V, K, w, h)
            fused = lambda: tiger.rasterize_gaussians(*a, check_finite=False)  # noqa: E731
            op_by_op = lambda: composite(project_for_raster(*a, settings=settings), w, h, settings)  # noqa: E731
            x, y = fused(), op_by_op()
            same = all(torch.equal(x[k], y[k]) for k in ("color", "alpha", "depth", "radii"))
            rows: dict[str, list[float]] = {"fused": [], "op_by_op": []}
            for _ in range(args.rounds):
                rows["fused"].append(cuda_time_ms(fused, iters=30))
                rows["op_by_op"].append(cuda_time_ms(op_by_op, iters=30))
            med = {k: sorted(v)[len(v) // 2] for k, v in rows.items()}
            print(f"{name}: forward ms (median of {args.rounds} medians of 30) fused {med['fused']:.3f} "
                  f"op-by-op {med['op_by_op']:.3f} ratio {med['fused'] / med['op_by_op']:.2f}; all: {rows}; "
                  f"identical outputs: {same}")


if __name__ == "__main__":
    main()
