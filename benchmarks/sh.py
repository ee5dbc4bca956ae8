"""Spherical harmonics (``tiger::sh_to_color``): forward and forward+backward time against the
error vs the float64 reference, side by side with gsplat's ``spherical_harmonics`` (same run,
when gsplat is importable), and the memory floor of each pass.

Inputs: N Gaussians, degree 3 (16 coefficients x 3 channels, float32), random directions and
coefficients, every Gaussian visible. Bytes that must move: forward reads the directions and
coefficients and writes the colours (N x (3 + 48 + 3) x 4 B); the backward also reads the colour
gradient and writes the direction and coefficient gradients (another N x (3 + 48 + 3) x 4 B).

    python -m benchmarks.sh                          # CPU
    python -m benchmarks.sh --device cuda --n 1e5 1e6 4e6
    python -m benchmarks.sh --device cuda --plain    # float32 rows through the plain kernels
"""
from __future__ import annotations

import argparse

import torch

from benchmarks.common import cpu_time_ms, cuda_time_ms, print_table, rel_err  # noqa: E402

from tiger.ops.sh import sh_to_color  # noqa: E402
from tiger.render.reference import sh_to_color_ref  # noqa: E402

BYTES_PER_GAUSSIAN = (3 + 48 + 3) * 4


def gsplat_sh():
    try:
        from gsplat import spherical_harmonics
    except ImportError:
        return None
    return lambda d, c, deg: spherical_harmonics(deg, d, c)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--n", type=float, nargs="+", default=None)
    ap.add_argument("--degree", type=int, default=3)
    ap.add_argument("--bandwidth-gbs", type=float, default=None,
                    help="measured copy bandwidth for the floor (default: measured here with a clone)")
    ap.add_argument("--plain", action="store_true",
                    help="CUDA float32 rows through the plain kernels instead of the staged ones "
                         "(sh_to_color's _staged=False; the same values), for comparison")
    args = ap.parse_args()
    cuda = args.device.startswith("cuda")
    sizes = [int(v) for v in (args.n or ([1e5, 1e6, 4e6] if cuda else [1e4, 1e5]))]
    timer = (lambda fn: cuda_time_ms(fn, iters=20, warmup=3)) if cuda else (lambda fn: cpu_time_ms(fn, iters=3))
    staged = not args.plain
    peers = {"tiger": lambda d, c, deg: sh_to_color(d, c, deg, _staged=staged)}
    if gsplat_sh() is not None and cuda:
        peers["gsplat"] = gsplat_sh()
    rows = []
    for n in sizes:
        g = torch.Generator().manual_seed(0)
        dirs = torch.randn(n, 3, generator=g)
        coeffs = torch.randn(n, 16, 3, generator=g) * 0.3
        v = torch.randn(n, 3, generator=g)
        want = sh_to_color_ref(dirs.double(), coeffs.double(), args.degree)
        d64, c64 = dirs.double().requires_grad_(), coeffs.double().requires_grad_()
        (sh_to_color_ref(d64, c64, args.degree) * v.double()).sum().backward()
        dirs, coeffs, v = dirs.to(args.device), coeffs.to(args.device), v.to(args.device)
        big = torch.empty(n * BYTES_PER_GAUSSIAN // 4, device=args.device)
        copy_ms = timer(lambda: big.clone())  # reads and writes the bytes of one pass
        bw = args.bandwidth_gbs or 2 * big.numel() * 4 / (copy_ms / 1e3) / 1e9
        floor_fwd = n * BYTES_PER_GAUSSIAN / (bw * 1e9) * 1e3
        for name, fn in peers.items():
            d = dirs.clone().requires_grad_()
            c = coeffs.clone().requires_grad_()

            def fwd() -> torch.Tensor:
                with torch.no_grad():
                    return fn(dirs, coeffs, args.degree)

            def fwd_bwd() -> None:
                d.grad = c.grad = None
                (fn(d, c, args.degree) * v).sum().backward()

            out = fwd().double().cpu()
            fwd_bwd()
            rows.append({"N": n, "impl": name, "fwd_ms": timer(fwd), "fwd+bwd_ms": timer(fwd_bwd),
                         "fwd_floor_ms": floor_fwd, "fwd+bwd_floor_ms": 2 * floor_fwd,
                         "err_color": rel_err(out, want), "err_v_coeffs": rel_err(c.grad.double().cpu(), c64.grad),
                         "err_v_dirs": rel_err(d.grad.double().cpu(), d64.grad)})
        if len(peers) > 1:
            ours, peer = rows[-2], rows[-1]
            print(f"N={n}: tiger/gsplat fwd {ours['fwd_ms'] / peer['fwd_ms']:.2f}, "
                  f"fwd+bwd {ours['fwd+bwd_ms'] / peer['fwd+bwd_ms']:.2f}", flush=True)
    print_table(rows, title=f"sh_to_color, degree {args.degree}, float32, {args.device} "
                            f"(error: relative to the float64 reference)")


if __name__ == "__main__":
    main()
