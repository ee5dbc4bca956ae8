"""SH colours of V views (``render_views``' SH step): V one-view calls, whose per-view coefficient
gradients autograd adds (the path before the V-view op), against one V-view call
(:func:`tiger.render.rasterize.sh_colors_views`: each coefficient row read once, the views'
gradients summed in the kernel), forward and forward+backward, in the same run.

Inputs: N Gaussians (default 317,600: the edit benchmark's scene), degree 3 as a scene stores it
(DC [N, 1, 3] and rest [N, 15, 3], float32), V cameras, 80 % of the Gaussians visible per view;
means, DC and rest require gradients (an edit's trainable Gaussians). The table also gives the
largest difference between the two paths' results (forward: 0, bit for bit; gradients: float
rounding, the views' sums are added in another order).

    python -m benchmarks.sh_views                              # CPU, N = 1e5
    python -m benchmarks.sh_views --device cuda --views 4 8    # the edit's 4 views and 8
"""
from __future__ import annotations

import argparse
from typing import Callable

import torch

from benchmarks.common import cpu_time_ms, cuda_time_ms, print_table

from tiger.render.rasterize import sh_colors, sh_colors_views


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--n", type=float, default=None, help="Gaussians (default: 317600 on CUDA, 1e5 on the CPU)")
    ap.add_argument("--views", type=int, nargs="+", default=[4])
    args = ap.parse_args()
    cuda = args.device.startswith("cuda")
    n = int(args.n or (317_600 if cuda else 1e5))
    timer: Callable[[Callable[[], object]], float] = (
        (lambda fn: cuda_time_ms(fn, iters=50, warmup=5)) if cuda else (lambda fn: cpu_time_ms(fn, iters=3)))
    g = torch.Generator().manual_seed(0)
    leaves = [torch.randn(n, 3, generator=g), torch.randn(n, 1, 3, generator=g),
              torch.randn(n, 15, 3, generator=g) * 0.3]
    means, dc, rest = [t.to(args.device).requires_grad_() for t in leaves]
    rows = []
    for views in args.views:
        vms = []
        for _ in range(views):
            vm = torch.eye(4)
            vm[:3, 3] = torch.randn(3, generator=g) * 3
            vms.append(vm.to(args.device))
        visible = (torch.rand(views, n, generator=g) > 0.2).to(args.device)
        v_colors = torch.randn(views, n, 3, generator=g).to(args.device)

        def per_view(backward: bool) -> list[torch.Tensor]:
            outs = [sh_colors(means, dc, vms[v], 3, visible[v], rest) for v in range(views)]
            if backward:
                torch.autograd.backward(outs, list(v_colors.unbind(0)))
            return outs

        def batched(backward: bool) -> list[torch.Tensor]:
            out = sh_colors_views(means, dc, vms, 3, visible, rest)
            if backward:
                out.backward(v_colors)
            return list(out.unbind(0))

        results = {}
        for name, fn in (("per-view calls", per_view), ("one V-view call", batched)):
            for t in (means, dc, rest):
                t.grad = None
            out = fn(True)
            results[name] = [torch.stack(out).detach()] + [t.grad.clone() for t in (means, dc, rest)]
            with torch.no_grad():
                fwd = timer(lambda: fn(False))
            rows.append({"V": views, "path": name, "fwd_ms": fwd, "fwd+bwd_ms": timer(lambda: fn(True))})
        a, b = results.values()
        diff = [float((x - y).abs().max()) for x, y in zip(a, b)]
        rows[-1].update({"max|diff| colour": diff[0], "means grad": diff[1], "dc grad": diff[2],
                         "rest grad": diff[3]})
        rows[-2].update({k: "" for k in rows[-1] if k not in rows[-2]})
    print_table(rows, title=f"SH colours of V views, N={n}, degree 3, float32, {args.device}")


if __name__ == "__main__":
    main()
