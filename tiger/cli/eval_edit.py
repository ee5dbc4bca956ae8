"""``tiger eval-edit``: edit metrics of a before/after pair of scenes (locality, CLIP direction)."""
from __future__ import annotations

import argparse
import json


from .common import (TAU_HELP, CliError, Summary, add_common, add_skip_missing, device_of, load_scene,
                     open_dataset, output_dir, parse_tau)
from .text import text_encoder


def add_parser(sub) -> None:
    p = sub.add_parser(
        "eval-edit", help="measure an edit: locality PSNR outside the object, CLIP direction metrics",
        description="Retrieve --target in both scenes with one threshold (the edited scene keeps its "
                    "language features, children inherit them), render both from cameras around the "
                    "object, and report locality (PSNR before vs after outside the object's dilated "
                    "footprint) and, with CLIP weights, the CLIP text-image direction similarity "
                    "(Instruct-NeRF2NeRF) between --caption-before and --caption-after and the CLIP "
                    "direction consistency between neighbouring views. Writes metrics.json.",
        epilog='example: tiger eval-edit outputs/demo/scene.ply outputs/demo/edit_red/edited.ply --target ball '
               '--caption-before "a blue ball" --caption-after "a red ball" --out outputs/demo/eval_red',
        formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("before", help="the scene before the edit (PLY with lang_*)")
    p.add_argument("after", help="the edited scene (PLY with lang_*)")
    p.add_argument("--target", required=True, help="text naming the edited object")
    add_common(p, models=True)
    p.add_argument("--text-embeddings", default=None, help="torch.save'd {text: [512] tensor} instead of CLIP")
    p.add_argument("--tau", type=parse_tau, default="auto",
                   help=TAU_HELP + "; chosen on the before scene and used on both")
    p.add_argument("--caption-before", default=None, help="caption of the original object (CLIP metrics)")
    p.add_argument("--caption-after", default=None, help="caption of the edited object (CLIP metrics)")
    p.add_argument("--views", type=int, default=8, help="cameras on the path around the object")
    p.add_argument("--size", type=int, default=256, help="render size (square)")
    p.add_argument("--dilate", type=int, default=4, help="footprint dilation in pixels for locality")
    p.add_argument("--data", default=None, help="the scene's dataset (360° vs forward-facing path)")
    add_skip_missing(p)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from tiger.edit.target import EmptyTargetError, resolve_target
    from tiger.edit.views import ObjectViews
    from tiger.eval.edit import clip_metrics, locality, locality_text
    from tiger.scene import render_rgb

    if args.views < 2:
        raise CliError("--views must be at least 2")
    if args.size < 16 or args.dilate < 0:
        raise CliError(f"--size must be >= 16 and --dilate >= 0, got {args.size} and {args.dilate}")
    dev = device_of(args.device)
    output_dir(args.out, args.force, create=False)  # refusals below leave no folder behind
    before, after = load_scene(args.before, dev), load_scene(args.after, dev)
    for name, s in ((args.before, before), (args.after, after)):
        if s.lang is None:
            raise CliError(f"{name} has no language features (lang_*); both scenes need them")
    enc = text_encoder(args.models, args.text_embeddings, dev, before, args.before)
    tau = args.tau
    try:
        tb = resolve_target(before, args.target, encoder=enc, tau=tau)
        ta = resolve_target(after, args.target, encoder=enc, tau=tb.tau)
    except EmptyTargetError as e:
        raise CliError(f"--target {args.target!r} retrieves no Gaussian: {e}") from e
    cams = None
    if args.data:
        cams = open_dataset(args.data, args.skip_missing).cameras
    if args.caption_before and args.caption_after and not hasattr(enc, "clip"):
        raise CliError("the CLIP metrics need CLIP weights (--models or $TIGER_MODELS), not a text table")
    path = ObjectViews(tb.center, tb.bbox_min, tb.bbox_max, capture=cams, force_360=True if not cams else None,
                       width=args.size, height=args.size).fixed(args.views)
    out = output_dir(args.out, args.force)
    report = {"target": args.target, "tau": tb.tau, "selected_before": tb.count, "selected_after": ta.count,
              "locality": locality(before, after, path, tb.mask, ta.mask, dilate_px=args.dilate)}
    if args.caption_before and args.caption_after:
        if not hasattr(enc, "clip"):
            raise CliError("the CLIP metrics need CLIP weights (--models or $TIGER_MODELS), not a text table")
        rb = render_rgb(before, path).permute(0, 3, 1, 2)
        ra = render_rgb(after, path).permute(0, 3, 1, 2)
        report["clip"] = clip_metrics(enc, rb, ra, args.caption_before, args.caption_after)
    from tiger.utils.io import atomic_write

    with atomic_write(out / "metrics.json", "w") as fh:
        json.dump(report, fh, indent=2)
    s = Summary("tiger eval-edit")
    s.add(locality_text(report["locality"], f"'{args.target}'"))
    if "clip" in report:
        c = report["clip"]
        s.add(f"CLIP direction similarity {c['clip_direction_similarity']:.4f}, "
              f"consistency {c.get('clip_direction_consistency', float('nan')):.4f}")
    s.add(f"details: {out / 'metrics.json'}")
    s.print()
    return 0
