"""``tiger info``: statistics of a scene file."""
from __future__ import annotations

import argparse

import torch

from .common import CliError, load_scene


def add_parser(sub) -> None:
    p = sub.add_parser("info", help="print a scene's statistics",
                       description="Print the number of Gaussians, SH degree, language features, "
                                   "bounds and opacity/scale statistics of a PLY scene.",
                       epilog="example: tiger info outputs/fox/scene.ply",
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("scene", help="PLY file (INRIA 3DGS layout, optional lang_*)")
    p.set_defaults(func=run)


def _q(x: torch.Tensor, qs=(0.0, 0.5, 1.0)) -> str:
    x = x.detach().double().reshape(-1)
    if x.numel() > 1_000_000:
        x = x[torch.randperm(x.numel())[:1_000_000]]
    return " / ".join(f"{float(torch.quantile(x, q)):.4g}" for q in qs)


def run(args: argparse.Namespace) -> int:
    s = load_scene(args.scene)
    n = len(s)
    if n == 0:
        raise CliError(f"{args.scene} holds no Gaussians")
    print(f"{args.scene}")
    print(f"  Gaussians        {n}")
    print(f"  SH degree        {s.sh_degree}")
    lang = "none" if s.lang is None else f"{s.lang.shape[1]}-d" + (
        ", with PCA basis" if s.lang_pca_basis is not None else ", no PCA basis")
    print(f"  language         {lang}")
    lo, hi = s.means.min(0).values, s.means.max(0).values
    print("  bounds           " + " ".join(f"[{float(a):.3g}, {float(b):.3g}]" for a, b in zip(lo, hi)))
    print(f"  opacity min/median/max  {_q(s.opacities)}")
    print(f"  scale   min/median/max  {_q(s.scales.max(1).values)}")
    for k, v in sorted(s.metadata.items()):
        print(f"  meta {k:<11} {v}")
    return 0
