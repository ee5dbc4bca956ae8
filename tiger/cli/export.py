"""``tiger export``: a scene in the compact formats web viewers load (.splat, .spz, compressed PLY)."""
from __future__ import annotations

import argparse
from pathlib import Path

from .common import CliError, Summary, load_scene, output_file


def add_parser(sub) -> None:
    from tiger.scene.export import FORMATS

    p = sub.add_parser(
        "export", help="write a scene as .splat, .spz or a compressed PLY for web viewers",
        description="Convert a PLY scene to the formats 3DGS web viewers share: 'splat' (antimatter15, "
                    "32 bytes a Gaussian, no view-dependent colour), 'spz' (Niantic, gzip, version 2, "
                    "SH kept, 5-8x smaller than the PLY on the demo and a random SH-3 scene; axes turned to "
                    "SPZ's right-up-back), "
                    "'ply-compressed' (PlayCanvas/SuperSplat, 256-Gaussian chunks, 16 bytes a Gaussian "
                    "plus 8-bit SH). Language features stay in the PLY. The layouts are described in "
                    "tiger/scene/export.py.",
        epilog="example: tiger export outputs/demo/scene.ply --format spz --out outputs/demo/scene.spz",
        formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("scene", help="PLY file")
    p.add_argument("--format", required=True, choices=FORMATS, help="output format")
    p.add_argument("--out", required=True, help="output file (e.g. scene.spz)")
    p.add_argument("--force", action="store_true", help="overwrite an existing output file")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from tiger.scene.export import export_scene

    scene = load_scene(args.scene)
    if len(scene) == 0:
        raise CliError(f"{args.scene} holds no Gaussians")
    out = output_file(args.out, args.force)
    size_before = Path(args.scene).stat().st_size
    path = export_scene(scene, out, args.format)
    s = Summary("tiger export")
    s.add(f"{len(scene)} Gaussians -> {path} ({args.format}, {path.stat().st_size / 1e6:.2f} MB; "
          f"the PLY: {size_before / 1e6:.2f} MB)")
    s.print()
    return 0
