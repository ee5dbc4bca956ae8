"""``tiger render``: views of a scene to PNG (and MP4/GIF): colour, depth, features, relevancy."""
from __future__ import annotations

import argparse

import torch

from .common import CliError, Summary, add_common, device_of, load_scene, output_dir

KINDS = ("color", "depth", "alpha", "features", "relevancy")


def add_parser(sub) -> None:
    p = sub.add_parser(
        "render", help="render views of a scene to pictures (and a video)",
        description="Render a scene from a dataset's cameras or an orbit: colour, depth, alpha, a "
                    "PCA picture of the language features, and relevancy heat maps of --query. "
                    "--video writes the colour frames as an MP4 (OpenCV or imageio-ffmpeg), else an "
                    "animated GIF.",
        epilog="example: tiger render outputs/fox/scene_lang.ply --orbit 36 --what color depth "
               "features --video --out outputs/fox/turntable",
        formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("scene", help="PLY file")
    add_common(p, models=True)
    p.add_argument("--data", default=None, help="render this dataset's cameras")
    p.add_argument("--orbit", type=int, default=8, help="orbit views when no --data (default: 8)")
    p.add_argument("--size", type=int, nargs=2, default=(640, 480), metavar=("W", "H"))
    p.add_argument("--what", nargs="+", choices=KINDS, default=["color", "depth"])
    p.add_argument("--query", default=None, help="text for the relevancy maps")
    p.add_argument("--text-embeddings", default=None)
    p.add_argument("--video", action="store_true", help="also write the colour frames as a video")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from tiger.utils.images import colorize, feature_pca_image, pca_basis, save_png

    from .query import pick_cameras

    dev = device_of(args.device)
    out = output_dir(args.out, args.force)
    scene = load_scene(args.scene, dev)
    if ("features" in args.what or "relevancy" in args.what) and scene.lang is None:
        raise CliError(f"{args.scene} has no language features: drop 'features'/'relevancy' from --what")
    if "relevancy" in args.what and not args.query:
        raise CliError("--what relevancy needs --query TEXT")
    if args.data:
        cams = pick_cameras(scene, args.data, 10**9, dev)
    else:
        from tiger.render.views import orbit_cameras_around

        cams = orbit_cameras_around(scene.means, args.orbit, args.size[0], args.size[1])
    summary = Summary("tiger render")
    frames, basis = [], None
    from tqdm.auto import tqdm

    for i, cam in enumerate(tqdm(cams, desc="rendering")):
        with torch.no_grad():
            r = scene.render(cam)
        name = getattr(cam, "image_name", "") or f"view{i:03d}"
        stem = "".join(c if c.isalnum() or c in "-_." else "_" for c in str(name))
        mask = r["alpha"] > 0.5
        if "color" in args.what:
            save_png(out / f"{stem}_color.png", r["color"].clamp(0, 1))
            frames.append(r["color"].clamp(0, 1))
        if "depth" in args.what:
            save_png(out / f"{stem}_depth.png", colorize(r["depth"], mask))
        if "alpha" in args.what:
            save_png(out / f"{stem}_alpha.png", r["alpha"])
        if "features" in args.what:
            from tiger.retrieval import render_language

            f, a = render_language(scene, cam)
            f = f / a.clamp_min(1e-6)[..., None]
            if basis is None:
                basis = pca_basis(f[a > 0.5].float().cpu(), 3)
            save_png(out / f"{stem}_features.png", feature_pca_image(f, a > 0.5, basis))
    if "relevancy" in args.what:
        from tiger.retrieval import write_relevancy_pictures

        from .text import text_encoder

        enc = text_encoder(args.models, args.text_embeddings, dev)
        write_relevancy_pictures(scene, cams, args.query, out, encoder=enc, score="relevancy")
    summary.add(f"{len(cams)} views x {', '.join(args.what)} -> {out}")
    if args.video and frames:
        from tiger.utils.video import write_video

        summary.add(f"video: {write_video(frames, out / 'turntable')}")
    summary.print()
    return 0
