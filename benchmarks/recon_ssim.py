"""SSIM (the 3DGS D-SSIM loss): run time of forward+backward against the error vs a
float64 SciPy reference, for each Gaussian-filter method of the tensor-op SSIM and for the fused
kernels (tiger::fused_ssim, "fused"), at each image size.

    python -m benchmarks.recon_ssim [--device cpu|cuda] [--threads N]
"""
from __future__ import annotations

import argparse
import time

import numpy as np
import torch
from scipy.ndimage import gaussian_filter

from tiger.recon.losses import ssim_map
from tiger.utils.filters import _blur, gaussian_blur


def ssim_ref(a: np.ndarray, b: np.ndarray) -> float:
    """Float64 SSIM, 11-tap Gaussian window (sigma 1.5), zero padding, mean over pixels."""
    f = lambda x: gaussian_filter(x, 1.5, mode="constant", cval=0.0, truncate=5 / 1.5)  # noqa: E731
    vals = []
    for c in range(a.shape[2]):
        x, y = a[..., c], b[..., c]
        mx, my = f(x), f(y)
        sxx, syy, sxy = f(x * x) - mx * mx, f(y * y) - my * my, f(x * y) - mx * my
        vals.append((2 * mx * my + 1e-4) * (2 * sxy + 9e-4) / ((mx * mx + my * my + 1e-4) * (sxx + syy + 9e-4)))
    return float(np.mean(vals))


def timed(fn, reps: int, sync, clock) -> float:
    fn()
    sync()
    t0 = clock()
    for _ in range(reps):
        fn()
    sync()
    return (clock() - t0) / reps * 1e3


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--threads", type=int, default=None)
    ap.add_argument("--sizes", default="64x64,240x135,480x270,960x540")
    ap.add_argument("--methods", default="fused,conv-autograd,conv,depthwise,matmul,shift")
    args = ap.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)
    dev = torch.device(args.device)
    sync = torch.cuda.synchronize if dev.type == "cuda" else (lambda: None)
    # on a shared CPU, process time (all threads) is steadier than wall time
    clock = time.perf_counter if dev.type == "cuda" else time.process_time
    methods = args.methods.split(",")
    what = "wall ms" if dev.type == "cuda" else "process CPU ms (all threads)"
    print(f"SSIM forward+backward on {dev} ({torch.get_num_threads()} threads, {what}), float32; "
          "error = |SSIM - float64 SciPy|")
    print("| H x W | " + " | ".join(f"{m} ms | {m} err" for m in methods) + " |")
    print("|---|" + "---:|---:|" * len(methods))
    rng = np.random.default_rng(0)
    for size in args.sizes.split(","):
        H, W = (int(v) for v in size.split("x"))
        a = rng.uniform(size=(H, W, 3))
        b = np.clip(a + rng.normal(scale=0.1, size=a.shape), 0, 1)
        ref = ssim_ref(a, b)
        ta = torch.from_numpy(a).float().to(dev).permute(2, 0, 1)[None].contiguous()
        tb = torch.from_numpy(b).float().to(dev).permute(2, 0, 1)[None].contiguous()
        cells = []
        for m in methods:
            x = ta.clone().requires_grad_(True)

            def step() -> torch.Tensor:
                x.grad = None
                if m == "fused":
                    s = ssim_map(x, tb, fused=True).mean()
                    s.backward()
                    return s
                C = x.shape[1]
                stack = torch.cat([x, tb, x * x, tb * tb, x * tb], 1)
                # "conv-autograd": the former path, autograd through conv2d (cuDNN's data gradient)
                mom = (_blur(stack, 11, 1.5, "conv", "zeros") if m == "conv-autograd"
                       else gaussian_blur(stack, method=m))
                mu1, mu2, e11, e22, e12 = mom.split(C, 1)
                s = ((2 * mu1 * mu2 + 1e-4) * (2 * (e12 - mu1 * mu2) + 9e-4)
                     / ((mu1 ** 2 + mu2 ** 2 + 1e-4) * (e11 - mu1 ** 2 + e22 - mu2 ** 2 + 9e-4))).mean()
                s.backward()
                return s

            reps = 20 if H * W <= 1e5 else 4
            ms = timed(step, reps, sync, clock)
            err = abs(float(step().detach()) - ref)
            cells.append(f"{ms:.2f} | {err:.1e}")
        print(f"| {H} x {W} | " + " | ".join(cells) + " |")


if __name__ == "__main__":
    main()
