#!/usr/bin/env python
"""Render a turntable of a 3DGS scene: N views on a circle around it, as PNGs and a video.

The scene is an INRIA-layout PLY (``tiger.scene.GaussianScene.load_ply``). The orbit's centre is
the median Gaussian position (or ``--center``), its radius ``--radius`` or, by default,
``--distance`` times the half diagonal of the box holding the central 90 % of the Gaussians per
axis. ``--up`` is the world's up direction: -y for COLMAP/OpenCV captures (the default),
+z for many NeRF/Blender scenes.

The video is an MP4 (OpenCV's encoder, else imageio-ffmpeg) when one is available, otherwise an
animated GIF written with Pillow (``--video gif|mp4|none`` forces one).

Example::

    python examples/render_turntable.py scene.ply --out outputs/turntable --views 60 \\
        --width 640 --height 480
"""
from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path
from typing import Optional, Sequence

import torch

def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                epilog="example: python examples/render_turntable.py scene.ply "
                                       "--out outputs/turntable --views 60")
    p.add_argument("ply", help="input Gaussian scene (INRIA-layout PLY)")
    p.add_argument("--out", required=True, help="output folder (frame_XXXX.png and turntable.mp4/gif)")
    p.add_argument("--views", type=int, default=36, help="number of views around the circle")
    p.add_argument("--width", type=int, default=480)
    p.add_argument("--height", type=int, default=360)
    p.add_argument("--fov", type=float, default=45.0, help="vertical field of view in degrees")
    p.add_argument("--elevation", type=float, default=25.0, help="camera elevation in degrees")
    p.add_argument("--radius", type=float, default=None, help="orbit radius (scene units)")
    p.add_argument("--distance", type=float, default=2.5,
                   help="radius as a multiple of the scene's robust half diagonal (without --radius)")
    p.add_argument("--center", type=float, nargs=3, default=None, metavar=("X", "Y", "Z"))
    p.add_argument("--up", type=float, nargs=3, default=(0.0, -1.0, 0.0), metavar=("X", "Y", "Z"),
                   help="world up direction (default 0 -1 0, the COLMAP/OpenCV habit)")
    p.add_argument("--background", type=float, nargs=3, default=(1.0, 1.0, 1.0), metavar=("R", "G", "B"))
    p.add_argument("--sh-degree", type=int, default=None, help="SH bands to use (default: all)")
    p.add_argument("--fps", type=int, default=24)
    p.add_argument("--video", choices=("auto", "mp4", "gif", "none"), default="auto")
    p.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    return p


def orbit_geometry(means: torch.Tensor, distance: float) -> tuple[torch.Tensor, float]:
    """(centre [3], radius) of an orbit that frames the central 90 % of ``means`` [N, 3]."""
    m = means.detach().double().cpu()
    lo, hi = torch.quantile(m, 0.05, dim=0), torch.quantile(m, 0.95, dim=0)
    half_diag = float((hi - lo).norm()) / 2
    return m.median(dim=0).values, max(half_diag, 1e-6) * distance


def main(argv: Optional[Sequence[str]] = None) -> int:
    args = build_parser().parse_args(argv)
    from tqdm.auto import tqdm

    from tiger.render.views import orbit_viewmats, pinhole_K
    from tiger.render import Camera
    from tiger.scene import GaussianScene
    from tiger.utils.images import save_png
    from tiger.utils.video import write_video

    if args.views < 1:
        raise SystemExit(f"render_turntable: --views must be >= 1, got {args.views}")
    if args.width < 1 or args.height < 1:
        raise SystemExit(f"render_turntable: image size must be positive, got {args.width}x{args.height}")
    ply = Path(args.ply)
    if not ply.is_file():
        raise SystemExit(f"render_turntable: PLY file not found: {ply}")
    scene = GaussianScene.load_ply(ply).to(args.device)
    center, radius = orbit_geometry(scene.means, args.distance)
    if args.center is not None:
        center = torch.tensor(args.center, dtype=torch.float64)
    if args.radius is not None:
        radius = args.radius
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    K = pinhole_K(args.width, args.height, args.fov)
    bg = torch.tensor(args.background, dtype=scene.dtype, device=scene.device)
    frames = []
    views = orbit_viewmats(args.views, center=center.tolist(), radius=radius,
                           elevation_deg=args.elevation, up=args.up)
    for i, V in enumerate(tqdm(views, desc="turntable")):
        cam = Camera(V, K, args.width, args.height, image_name=f"frame_{i:04d}")
        with torch.no_grad():
            r = scene.render(cam, background=bg, sh_degree=args.sh_degree)
        img = r["color"].clamp(0, 1).cpu()
        save_png(out / f"frame_{i:04d}.png", img)
        frames.append(img)
    try:
        video = write_video(frames, out / "turntable", args.fps, args.video)
    except RuntimeError as exc:  # --video mp4 without an encoder
        raise SystemExit(f"render_turntable: {exc} (--video gif)") from exc
    print(f"{scene!r}: {args.views} views at radius {radius:.3f} around "
          f"({', '.join(f'{float(c):.3f}' for c in center)}) -> {out}/frame_*.png"
          + (f", {video}" if video else ""))
    return 0


def cli(argv: Optional[Sequence[str]] = None) -> int:
    """``main`` with bad input reported in one line (SystemExit with the message), no traceback."""
    from tiger.scene import SceneFormatError

    try:
        return main(argv)
    except (SceneFormatError, FileNotFoundError, KeyError) as exc:
        raise SystemExit(f"render_turntable: {exc}") from exc


if __name__ == "__main__":
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    sys.exit(cli())
