"""``tiger render``: views of a scene to PNG (and MP4/GIF): colour, depth, features, relevancy."""
from __future__ import annotations

import argparse
from typing import Iterator

import torch

from tiger.render import Camera
from tiger.scene import GaussianScene, render_view_chunks

from .common import (CliError, Summary, add_common, add_skip_missing, check_render_size, device_of, load_scene,
                     output_dir, positive_size, views_per_pass)

KINDS = ("color", "depth", "alpha", "features", "relevancy")


def add_parser(sub) -> None:
    p = sub.add_parser(
        "render", help="render views of a scene to pictures (and a video)",
        description="Render a scene: colour, depth, alpha, a PCA picture of the language features, "
                    "and relevancy heat maps of --query. Views: --views of the capture's own camera "
                    "path (the cameras.json that `tiger reconstruct` writes beside the PLY, or "
                    "--data's cameras); without cameras, or with --orbit N, N views on an arc over "
                    "the side the scene was observed from (judged from its view-dependent colour). "
                    "Pictures are named after the source image (0001_color.png). --video writes "
                    "the colour frames as an H.264 MP4 that browsers play (imageio-ffmpeg or OpenCV), else an "
                    "animated GIF. Depth pictures carry a colour bar in scene units. --what relevancy "
                    "shows the score `tiger query` selects with (--score, same default): the cosine "
                    "over [-1, 1], or the LERF relevancy over [0.5, 1] (0.5: no more relevant than "
                    "the canonical negatives 'object', 'things', 'stuff', 'texture').",
        epilog="example: tiger render outputs/fox/scene_lang.ply --views 12 --downscale 2 --what color "
               "depth features --video --out outputs/fox/views",
        formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("scene", help="PLY file")
    add_common(p, models=True)
    p.add_argument("--data", default=None,
                   help="render this dataset's cameras (default: cameras.json beside the PLY)")
    add_skip_missing(p)
    p.add_argument("--views", default=None, metavar="N|I,J,...",
                   help="which views of the camera path: a count evenly spread (default: 8), "
                        "comma-separated indices (0,12,24; one index: 12,) or 'all'")
    p.add_argument("--downscale", type=float, default=1.0,
                   help="render at 1/F of the cameras' resolution (default: 1)")
    p.add_argument("--orbit", type=int, default=None, metavar="N",
                   help="N views on an arc over the observed side instead of the capture's cameras "
                        "(the default when there are none: 8)")
    p.add_argument("--size", type=int, nargs=2, default=(640, 480), metavar=("W", "H"),
                   help="picture size of --orbit views (default: 640 480)")
    p.add_argument("--what", nargs="+", choices=KINDS, default=["color", "depth"])
    p.add_argument("--query", default=None, help="text for the relevancy maps")
    p.add_argument("--score", choices=("cosine", "relevancy"), default="cosine",
                   help="what --what relevancy shows (as `tiger query --score`; default: %(default)s)")
    p.add_argument("--text-embeddings", default=None)
    p.add_argument("--video", action="store_true", help="also write the colour frames as a video")
    p.set_defaults(func=run)


def _cameras(args: argparse.Namespace, scene: GaussianScene,
             dev: torch.device) -> tuple[list[Camera], str]:
    """The views to render and where they come from (see the command's description)."""
    from tiger.render.views import path_view_indices
    from tiger.scene.observed import observed_orbit_cameras
    from tiger.scene.cameras_json import cameras_json_path, read_cameras_json

    if not args.downscale > 0:
        raise CliError(f"--downscale must be positive, got {args.downscale}")
    stored = cameras_json_path(args.scene)
    if args.orbit is not None or (not args.data and not stored.is_file()):
        n = 8 if args.orbit is None else args.orbit
        if n <= 0:
            raise CliError(f"--orbit must be positive, got {n}")
        if args.views is not None:
            raise CliError("--views picks views of a camera path; with an orbit give the count as --orbit N")
        w, h = (max(1, round(v / args.downscale)) for v in positive_size(*args.size))
        return observed_orbit_cameras(scene, n, w, h), f"arc over the observed side, {w}x{h}"
    if args.data:
        from .query import pick_cameras

        path, source = pick_cameras(scene, args.data, 10**9, dev, args.skip_missing), f"cameras of {args.data}"
    else:
        path, source = read_cameras_json(stored), f"capture path in {stored}"
    try:
        idx = list(range(len(path))) if args.views == "all" else path_view_indices(len(path), args.views)
    except ValueError as e:
        raise CliError(f"--views: {e}") from None
    cams = [path[i].scaled(args.downscale) if args.downscale != 1 else path[i] for i in idx]
    return cams, f"{len(cams)} of {len(path)} {source}"


def _renders(scene: GaussianScene, cams: list[Camera], per_pass: int) -> Iterator[dict[str, torch.Tensor]]:
    """Each view's 'color' [H, W, 3], 'alpha' and 'depth' [H, W], rendered up to ``per_pass`` views
    of one size at a time (:func:`tiger.scene.render_view_chunks`), the same pictures as one render
    each."""
    # a detached scene, not no_grad: grad mode set around a yield would hold in the caller too
    for _, chunk in render_view_chunks(scene.detach(), cams, views_per_pass=per_pass):
        for v in range(chunk["color"].shape[0]):
            yield {key: chunk[key][v] for key in ("color", "alpha", "depth")}


def _stems(cams: list[Camera]) -> list[str]:
    """File stems: the source image's name without folder or extension (0001), made unique."""
    from pathlib import Path

    from tiger.utils.io import unique_file_slugs

    names = [Path(cam.image_name or f"view{i:03d}").stem for i, cam in enumerate(cams)]
    return unique_file_slugs(names, [f"view{i:03d}" for i in range(len(cams))], keep="-_", max_len=None)


def run(args: argparse.Namespace) -> int:
    from tiger.utils.images import depth_picture, feature_pca_image, pca_basis, save_png

    positive_size(*args.size)
    dev = device_of(args.device)
    output_dir(args.out, args.force, create=False)  # refusals below leave no folder behind
    scene = load_scene(args.scene, dev)
    if ("features" in args.what or "relevancy" in args.what) and scene.lang is None:
        raise CliError(f"{args.scene} has no language features: drop 'features'/'relevancy' from --what")
    if "relevancy" in args.what and not args.query:
        raise CliError("--what relevancy needs --query TEXT")
    enc = None
    if "relevancy" in args.what:
        from .text import text_encoder

        enc = text_encoder(args.models, args.text_embeddings, dev, scene, args.scene)
        enc.encode_text([args.query])  # an unknown text is refused before anything is written
    cams, source = _cameras(args, scene, dev)
    if not cams:
        raise CliError("no views to render")
    channels = scene.lang.shape[1] if "features" in args.what or "relevancy" in args.what else 3
    width, height = max((c.width, c.height) for c in cams)
    check_render_size(width, height, dev, channels=channels,
                      option="--size" if source.startswith("arc") else "the cameras' size (--downscale)")
    out = output_dir(args.out, args.force)
    summary = Summary("tiger render")
    frames, basis = [], None
    from tiger.utils.progress import progress

    renders = _renders(scene, cams, views_per_pass(width, height, dev))
    for cam, stem, r in zip(cams, _stems(cams), progress(renders, "rendering", total=len(cams))):
        mask = r["alpha"] > 0.5
        if "color" in args.what:
            save_png(out / f"{stem}_color.png", r["color"].clamp(0, 1))
            frames.append(r["color"].clamp(0, 1))
        if "depth" in args.what:
            save_png(out / f"{stem}_depth.png", depth_picture(r["depth"], mask))
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

        write_relevancy_pictures(scene, cams, args.query, out, encoder=enc, score=args.score)
    summary.add(f"{len(cams)} views ({source}) x {', '.join(args.what)} -> {out}")
    if args.video and frames:
        from tiger.utils.video import write_video

        summary.add(f"video: {write_video(frames, out / 'turntable')}")
    summary.print()
    return 0
