"""``tiger query``: text -> the Gaussians it names, with pictures and a PLY of the selection."""
from __future__ import annotations

import argparse
import json
from typing import Optional

import torch

from tiger.render import Camera
from tiger.scene import GaussianScene, render_view_chunks
from tiger.utils.io import atomic_write, unique_file_slugs

from .common import (CliError, Summary, add_common, add_selection_options, add_skip_missing, device_of, load_scene,
                     open_dataset, output_dir, views_per_pass, warn)
from .text import text_encoder


def add_parser(sub) -> None:
    p = sub.add_parser(
        "query", help="retrieve the Gaussians a text names; write pictures and the selection",
        description="Encode the text with CLIP (templates averaged), project it with the scene's "
                    "PCA, score every Gaussian (cosine, or LERF relevancy against canonical "
                    "negatives), select s > tau, and write the selection as a PLY, relevancy heat "
                    "maps and a highlighted render for a few views, and the object's centre and "
                    "bounding box (selection.json).",
        epilog='example: tiger query outputs/fox/scene_lang.ply "fox ears" --data ../shared/data/fox '
               "--out outputs/fox/query_ears",
        formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("scene", help="PLY with lang_* features and their PCA basis, or a `tiger prepare` folder")
    p.add_argument("text", nargs="+", help="one or more queries")
    add_common(p, models=True)
    p.add_argument("--text-embeddings", default=None,
                   help="torch.save'd {text: [512] tensor} instead of CLIP weights")
    p.add_argument("--data", default=None, help="dataset whose cameras to draw (default: an orbit)")
    add_skip_missing(p)
    p.add_argument("--views", type=int, default=3, help="pictures per query")
    add_selection_options(p, guarded=False)
    p.set_defaults(func=run)


def pick_cameras(scene: GaussianScene, data: Optional[str], n: int,
                 device: torch.device, skip_missing: bool = False) -> list[Camera]:
    """n cameras from a dataset (evenly spread) or an orbit around the scene."""
    if data:
        cams = open_dataset(data, skip_missing).cameras
        step = max(len(cams) // max(n, 1), 1)
        return [c.to(device) for c in cams[::step][:n]]
    from tiger.render.views import orbit_cameras_around

    return orbit_cameras_around(scene.means, n, 480, 360)


def run(args: argparse.Namespace) -> int:
    from tiger.retrieval import check_selection, retrieve, write_relevancy_pictures
    from tiger.utils.images import save_png

    # Everything that can refuse runs before the output folder is made: a refused query
    # leaves nothing behind, and no text's outputs are written unless every text is known.
    if args.views < 0:
        raise CliError(f"--views must be >= 0 (pictures per query), got {args.views}")
    dev = device_of(args.device)
    output_dir(args.out, args.force, create=False)
    scene = load_scene(args.scene, dev)
    if scene.lang is None:
        raise CliError(f"{args.scene} has no language features (lang_*); run `tiger embed` first")
    tau = args.tau
    encoder = text_encoder(args.models, args.text_embeddings, dev, scene, args.scene)
    texts = list(dict.fromkeys(args.text))
    try:
        results = {text: retrieve(scene, text, encoder=encoder, score=args.score, tau=tau) for text in texts}
    except (KeyError, ValueError) as e:
        raise CliError(f"{e.args[0] if e.args else e}; nothing was written") from None
    cams = pick_cameras(scene, args.data, args.views, dev, args.skip_missing)
    per_pass = views_per_pass(max(c.width for c in cams), max(c.height for c in cams), dev) if cams else 1
    out = output_dir(args.out, args.force)
    summary = Summary("tiger query")
    report = {}
    # the highlight pictures' fixed parts, once for all texts
    frozen, rgb = scene.detach(), scene.rgb.detach()
    orange, white = rgb.new_tensor([1.0, 0.5, 0.0]), rgb.new_ones(3)
    for text, slug in zip(texts, unique_file_slugs(texts)):
        r = results[text]
        check = check_selection(scene.means, r.mask)
        if not check.ok:
            warn(f"{text!r}: {check.problem}; see the highlight pictures and choose --tau or --score")
        if r.count:
            scene.subset(r.mask).save_ply(out / f"{slug}.ply")
        write_relevancy_pictures(scene, cams, text, out / "relevancy", encoder=encoder,
                                 score=args.score)
        tint = torch.where(r.mask[:, None], 0.4 * rgb + 0.6 * orange, 0.35 * rgb + 0.3)
        for first, chunk in render_view_chunks(frozen, cams, tint, background=white, views_per_pass=per_pass):
            for v, img in enumerate(chunk["color"]):
                save_png(out / f"{slug}_highlight_{first + v}.png", img)
        report[text] = {"selected": r.count, "tau": r.tau, "score": r.score, "files": slug,
                        "warning": check.problem,
                        "center": None if r.center is None else r.center.tolist(),
                        "bbox_min": None if r.bbox_min is None else r.bbox_min.tolist(),
                        "bbox_max": None if r.bbox_max is None else r.bbox_max.tolist()}
        summary.add(f"{text!r}: {r.count} of {len(scene)} Gaussians (tau {r.tau:.3f})"
                    + (f" -> {out / (slug + '.ply')}" if r.count else ""))
    with atomic_write(out / "selection.json", "w") as fh:
        json.dump(report, fh, indent=2)
    summary.add(f"pictures in {out}, details in {out / 'selection.json'}")
    summary.print()
    return 0
