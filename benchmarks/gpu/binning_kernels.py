"""Every GPU operation of one tile-binning call, in launch order, with its duration.

The per-stage tables of ``real_scenes.py`` sum kernels by name, so the passes of the two CUB
radix sorts (the depth sort over N keys, the tile sort over M pairs) show as one line. This
script profiles single ``tiger.bin_gaussians`` calls (after warm-up) and lists each GPU
operation: the onesweep passes of each sort, the count/emit kernels and the memsets, in µs,
median over ``--reps`` calls. Cases as in ``real_scenes.py`` (snowmiku-1080p by default).

    python -m benchmarks.gpu.binning_kernels --cases snowmiku-1080p,standard
"""
from __future__ import annotations

import argparse
import statistics
from pathlib import Path

import torch

REPO = Path(__file__).resolve().parents[2]
from tests.render.standard_scenes import heavy_tailed_scene, standard_camera, standard_scene  # noqa: E402
from benchmarks.gpu.real_scenes import project, snowmiku  # noqa: E402

import tiger  # noqa: E402,F401  (registers the ops)


def gpu_ops_of_one_call(fn, reps: int) -> list[tuple[str, float]]:
    """(name, median µs) of each GPU operation of ``fn()``, in launch order."""
    from torch.autograd import DeviceType
    from torch.profiler import ProfilerActivity, profile

    for _ in range(3):
        fn()
    torch.cuda.synchronize()
    runs: list[list[tuple[str, float]]] = []
    for _ in range(reps):
        with profile(activities=[ProfilerActivity.CUDA]) as prof:
            fn()
            torch.cuda.synchronize()
        ev = sorted((e for e in prof.events() if e.device_type == DeviceType.CUDA),
                    key=lambda e: e.time_range.start)
        runs.append([(e.name, e.time_range.elapsed_us()) for e in ev])
    n = min(len(r) for r in runs)
    return [(runs[0][i][0], statistics.median(r[i][1] for r in runs)) for i in range(n)]


def short(name: str) -> str:
    for key in ("Onesweep", "Histogram", "ExclusiveSum", "DeviceScanInit", "DeviceScanKernel"):
        if key in name:
            return f"cub {key}"
    return name.split("(")[0].replace("void ", "")[:70]


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--cases", default="snowmiku-1080p")
    p.add_argument("--reps", type=int, default=7)
    p.add_argument("--snowmiku", type=Path, default=REPO / ".carry" / "realscene" / "snowmiku")
    args = p.parse_args()
    for case in args.cases.split(","):
        if case.startswith("snowmiku"):
            sc, V, K, w, h = snowmiku(args.snowmiku, 1080 if case.endswith("1080p") else 2968, "cuda")
        elif case in ("standard", "heavy"):
            sc = (standard_scene if case == "standard" else heavy_tailed_scene)(1_000_000, 3, device="cuda")
            w, h = 1920, 1080
            V, K = standard_camera(w, h, device="cuda")
        else:
            raise SystemExit(f"unknown case {case!r}")
        m2, cn, d, op, r = project(sc, V, K, w, h)
        ops = gpu_ops_of_one_call(
            lambda: torch.ops.tiger.bin_gaussians(m2, cn, op, d, r, w, h, 16, 1 / 255), args.reps)
        print(f"== {case} {w}x{h}: N={m2.shape[0]}, one bin_gaussians call, median of {args.reps}")
        total = 0.0
        for i, (name, us) in enumerate(ops):
            total += us
            print(f"{i:3d} {us:8.1f} us  {short(name)}")
        print(f"    {total:8.1f} us  total GPU time\n", flush=True)


if __name__ == "__main__":
    main()
