"""``tiger delete``: remove what a text names, inpaint the views, refit; write the new scene and pictures."""
from __future__ import annotations

import argparse
import math
from pathlib import Path

import torch

from .common import (CliError, Summary, add_common, add_selection_options, add_skip_missing,
                     check_selection_or_refuse, claim_output, device_of, finish_output, load_scene,
                     open_dataset, output_dir, run_settings)
from .text import text_encoder


def add_parser(sub) -> None:
    p = sub.add_parser(
        "delete", help="delete the object a text names: remove, inpaint the views, refit",
        description="Retrieve the Gaussians the text names (plus the floaters inside the object's "
                    "box that are still fairly relevant), remove them, render the rest into the "
                    "views (the capture's with --data, otherwise views around the object), find "
                    "the holes (where the object was and little remains), inpaint them (OpenCV "
                    "Telea built in, or LaMa big-lama.pt), and refit only the Gaussians around the "
                    "holes. Writes scene.ply, before/after pictures of 4 views, the hole masks and "
                    "inpainted views, and delete.json (counts, per-stage times, metrics).",
        epilog='example: tiger delete outputs/demo/scene.ply "mug" --text-embeddings '
               "outputs/demo/text_embeddings.pt --out outputs/demo/delete_mug",
        formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("scene", help="PLY with lang_* features and their PCA basis, or a `tiger prepare` folder")
    p.add_argument("text", help="what to delete")
    add_common(p, models=True)
    p.add_argument("--data", default=None, help="the capture (COLMAP or transforms.json) whose views to "
                                                 "inpaint and refit on (default: views around the object)")
    add_skip_missing(p)
    p.add_argument("--inpainter", choices=("opencv", "lama"), default="opencv",
                   help="opencv: Telea (built in); lama: big-lama.pt from --models/$TIGER_MODELS/lama")
    p.add_argument("--text-embeddings", default=None,
                   help="torch.save'd {text: [512] tensor} instead of CLIP weights")
    add_selection_options(p, guarded=True)
    p.add_argument("--views", type=int, default=12,
                   help="views around the object without --data; the most of the capture's with it")
    p.add_argument("--size", default="320x240", help="WxH of the views around the object")
    p.add_argument("--downscale", type=float, default=1.0, help="image downscale with --data")
    p.add_argument("--steps", type=int, default=150, help="refit steps (one view each)")
    p.add_argument("--dilate", type=int, default=3, help="hole dilation in pixels")
    p.add_argument("--background", default="0,0,0", help="R,G,B behind the scene, in [0, 1]")
    p.add_argument("--resume", action="store_true",
                   help="continue the refit from --out's checkpoint; refused, naming what differs, when "
                        "--out holds a deletion with another scene, text or settings")
    p.set_defaults(func=run)


def _size(text: str) -> tuple[int, int]:
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise CliError(f"--size must be WxH, e.g. 320x240, got {text!r}") from None
    if w <= 0 or h <= 0:
        raise CliError(f"--size must be positive, got {text!r}")
    return w, h


def _dataset_views(data: str, n: int, downscale: float, device, skip_missing: bool = False):
    from tiger.scene.images import load_image

    cams = open_dataset(data, skip_missing).cameras
    step = max(math.ceil(len(cams) / max(n, 1)), 1)
    loaded = [load_image(c, downscale) for c in cams[::step]]
    return [c.to(device) for _, c in loaded], torch.stack([im for im, _ in loaded]).to(device)


def run(args: argparse.Namespace) -> int:
    from tiger.delete import DeleteConfig, delete, views_around

    dev = device_of(args.device)
    if args.resume and not Path(args.out).is_dir():
        raise CliError(f"--resume: {args.out} has no earlier run to resume")
    settings = run_settings(args)
    output_dir(args.out, args.force or args.resume, create=False)  # refusals below leave nothing behind
    scene = load_scene(args.scene, dev)
    if scene.lang is None:
        raise CliError(f"{args.scene} has no language features (lang_*); run `tiger embed` first")
    try:
        bg = tuple(float(v) for v in args.background.split(","))
    except ValueError:
        bg = ()
    if len(bg) != 3 or not all(0.0 <= v <= 1.0 for v in bg):
        raise CliError(f"--background must be R,G,B with each in [0, 1], got {args.background!r}")
    if args.steps < 0 or args.views <= 0 or args.dilate < 0:
        raise CliError("--steps and --dilate must be >= 0 and --views > 0")
    size = _size(args.size)
    tau = args.tau
    cfg = DeleteConfig(score=args.score, tau=tau, steps=args.steps, dilate=args.dilate, background=bg)
    encoder = text_encoder(args.models, args.text_embeddings, dev, scene, args.scene)
    from tiger.retrieval import CANONICAL_NEGATIVES, retrieve

    retrieval = retrieve(scene, args.text, encoder=encoder, score=args.score, tau=tau,
                         negatives=CANONICAL_NEGATIVES if args.score == "relevancy" else None)
    if retrieval.count == 0:
        raise CliError(f"{args.text!r} selected no Gaussian ({args.score} > {retrieval.tau:.3f}); "
                       "nothing to delete (try a lower --tau)")
    check_selection_or_refuse(scene, retrieval.mask, args.text, args.force, "delete")
    out = claim_output(args.out, "delete", settings, force=args.force, resume=args.resume)
    images = None
    if args.data:
        cams, images = _dataset_views(args.data, args.views, args.downscale, dev, args.skip_missing)
    else:
        cams = [c.to(dev) for c in views_around(retrieval, args.views, *size)]
    res = delete(scene, retrieval, cams, images, inpainter=args.inpainter, encoder=encoder, config=cfg,
                 checkpoint_dir=out, resume=args.resume, models=args.models)
    from tiger.eval.reprojection import evaluate_delete

    evaluate_delete(res, cfg.background)  # measured here, as `tiger edit` measures its locality
    res.save(out, extra={"text": args.text, "inpainter": args.inpainter, "scene": str(args.scene),
                         "data": args.data, "config": vars(cfg)})
    finish_output(out, "delete")
    summary = Summary("tiger delete")
    c, t, m = res.counts, res.timings, res.metrics
    summary.add(f"removed {c['removed']} Gaussians ({c['retrieved'] - c['stray_kept']} retrieved + {c['floaters']} "
                f"floaters + {c['unseen']} unseen + {c['similar']} similar; {c['stray_kept']} retrieved far "
                "from the object kept) "
                f"of {c['total']}; {c['trainable']} trainable, {c['seeded']} seeded; {c['final']} now")
    summary.add("time: " + ", ".join(f"{k} {v:.1f} s" for k, v in t.items()))
    summary.add(f"locality PSNR {m['locality_psnr']:.1f} dB outside the object; hole PSNR "
                f"{m['hole_psnr']:.1f} dB vs the inpainted views")
    summary.add(f"{out / 'scene.ply'}; pictures in {out}; details in {out / 'delete.json'}")
    summary.print()
    return 0
