"""The fox image against gsplat's with tiger's alpha clamp (0.99: SPEC §3's alpha_max, INRIA's
value) and with gsplat's (0.999): relative and largest absolute difference of the C = 3 image, and
how many Gaussians of the trained scene are above each clamp. The fox is trained here, as
``benchmarks.gpu.real_scenes`` trains it (3,000 steps). Needs gsplat.
Usage: python -m benchmarks.gpu.alpha_clamp_vs_gsplat [--fox-data PATH]"""
from __future__ import annotations

import argparse
from pathlib import Path

import torch

import tiger
from benchmarks.common import rel_err
from benchmarks.gpu.rasterize_vs_gsplat import gsplat_render
from benchmarks.gpu.real_scenes import fox


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--fox-data", type=Path, default=Path(".carry/realscene/fox"))
    p.add_argument("--iterations", type=int, default=3000)
    args = p.parse_args()
    sc, V, K, w, h, info = fox(args.fox_data, "cuda", args.iterations, 90.0, Path("/tmp/tiger_fox_cache"))
    o = sc["opacities"]
    print(f"# python -m benchmarks.gpu.alpha_clamp_vs_gsplat, {torch.cuda.get_device_name()}")
    print(f"fox: {info}; opacity > 0.99: {int((o > 0.99).sum())} of {o.numel()}, > 0.999: {int((o > 0.999).sum())}")
    with torch.no_grad():
        b = gsplat_render(sc, V, K, w, h)[0]
        for alpha_max in (0.99, 0.999):
            a = tiger.rasterize_gaussians(sc["means"], sc["quats"], sc["scales"], sc["opacities"], sc["colors"],
                                          V, K, w, h, check_finite=False, alpha_max=alpha_max)["color"]
            print(f"alpha_max {alpha_max}: image vs gsplat rel {rel_err(a, b):.3g}, "
                  f"max abs {float((a - b).abs().max()):.3g}")


if __name__ == "__main__":
    main()
