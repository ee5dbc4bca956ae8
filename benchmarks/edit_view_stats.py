"""What the edit loop's views ask of the rasterizer: screen radii, bounding-box tiles and tile
intersections of each of 4 object-centred views (``ObjectViews.fixed``) of the edit benchmark's
scene (benchmarks/edit.py's demo tabletop, target "ball"), with the statistics of the real-scene
benchmark (``benchmarks/gpu/real_scenes.radii_stats``). CPU; about a second per view.

    python -m benchmarks.edit_view_stats [--density 16] [--size 512]
"""
from __future__ import annotations

import argparse

import torch

from benchmarks.common import print_table  # noqa: E402
from benchmarks.edit import demo_scene  # noqa: E402
from benchmarks.gpu.real_scenes import radii_stats  # noqa: E402

from tiger.edit import resolve_target  # noqa: E402
from tiger.edit.views import ObjectViews  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--density", type=float, default=16.0)
    ap.add_argument("--size", type=int, default=512)
    args = ap.parse_args()
    scene, query = demo_scene(args.density, "cpu")
    tgt = resolve_target(scene, query, tau=0.5)
    views = ObjectViews(tgt.center, tgt.bbox_min, tgt.bbox_max, force_360=True, width=args.size, height=args.size)
    tensors = {"means": scene.means, "quats": scene.quats, "scales": scene.scales, "opacities": scene.opacities}
    rows = []
    for i, cam in enumerate(views.fixed(4)):
        cam = cam.to(dtype=scene.dtype)
        rows.append({"view": i, **radii_stats(tensors, cam.viewmat, cam.K, args.size, args.size)})
    print_table(rows, title=f"edit views: {len(scene)} Gaussians ({tgt.count} editable), {args.size}x{args.size}")


if __name__ == "__main__":
    main()
