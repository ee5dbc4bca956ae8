"""``tiger embed``: train each Gaussian's 64-d language embedding from cached feature maps."""
from __future__ import annotations

import argparse

from .common import (CliError, Summary, add_common, add_skip_missing, check_record, device_of, existing, load_scene,
                     open_dataset, output_file, run_settings, write_record)


def add_parser(sub) -> None:
    from tiger.language.field import FieldConfig

    p = sub.add_parser(
        "embed", help="train the language field of a scene from feature maps",
        description="Optimise only each Gaussian's language embedding L (Adam) so that rendered "
                    "features match the maps written by `tiger features`; geometry stays frozen "
                    "and the features-only backward computes no geometry gradient. The maps are "
                    "read once (kept on the GPU when they fit, else streamed from pinned memory) and "
                    "each view is projected and binned once. "
                    "Writes a PLY with lang_* and the PCA basis.",
        epilog="example: tiger embed outputs/fox/scene.ply ../shared/data/fox "
               "--features outputs/fox/features --out outputs/fox/scene_lang.ply\n\n"
               "The defaults start from the lifted embeddings, train first on coarse maps, then at full resolution on "
               "bands of at most\nhalf a million pixels, with a decaying learning rate; the earlier default "
               "(10,000 steps of whole views at a constant\nrate) is --steps 10000 --coarse 0 --lr 2.5e-3 "
               "--lr-final 1 --crop-pixels 0.",
        formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("scene", help="input PLY")
    p.add_argument("data", help="the dataset the features were extracted from (for the cameras)")
    p.add_argument("--features", required=True, help="folder written by `tiger features`")
    add_common(p)
    add_skip_missing(p)
    d = FieldConfig()
    p.add_argument("--steps", type=int, default=d.steps,
                   help=f"training steps (default {d.steps}); 0 with --init lift: the lifted embeddings as they are")
    p.add_argument("--coarse", type=float, default=d.coarse,
                   help=f"fraction of the steps (the first ones) that train on maps averaged over --coarse-factor "
                        f"blocks, the views rendered at that size (default {d.coarse}; views under 2^18 pixels are "
                        "never pooled; 0: all at full resolution)")
    p.add_argument("--coarse-factor", type=int, default=d.coarse_factor,
                   help=f"block size of the coarse maps in pixels (default {d.coarse_factor})")
    p.add_argument("--init", choices=("lift", "random"), default="lift",
                   help="starting embeddings: 'lift' (default: each Gaussian's blending-weighted mean of the "
                        "maps, one pass over the views) or 'random'")
    p.add_argument("--lr", type=float, default=d.lr, help=f"Adam learning rate at the first step (default {d.lr})")
    p.add_argument("--lr-final", type=float, default=d.lr_final,
                   help=f"learning rate at the last step as a fraction of --lr, decaying exponentially "
                        f"(default {d.lr_final}; 1: constant)")
    p.add_argument("--crop-pixels", type=int, default=d.crop_pixels,
                   help=f"pixels of a view each step renders at most: a full-width band of rows at a random "
                        f"height (default {d.crop_pixels}, a quarter of a 1080x1920 view; smaller views are "
                        "rendered whole; 0: always whole views)")
    p.add_argument("--batch-views", type=int, default=d.batch_views, help="views per step")
    p.add_argument("--loss", choices=("l1", "l2", "cosine"), default=d.loss)
    p.add_argument("--checkpoint", default=None,
                   help="checkpoint file (default: OUT + .ckpt.pt), written every 1000 steps, at the end "
                        "and on Ctrl-C; an existing one is continued exactly (one made with other "
                        "settings is refused, naming what differs)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from pathlib import Path

    from tiger.language.extract import FeatureSet
    from tiger.language.field import train_field
    from tiger.language.pca import PCABasis

    dev = device_of(args.device)
    out = output_file(args.out, args.force)
    # an interrupted run's checkpoint is continued: only with the same inputs and settings
    ckpt = args.checkpoint or str(out) + ".ckpt.pt"
    record, settings = Path(ckpt + ".run.json"), run_settings(args, ignore=("checkpoint",))
    if Path(ckpt).is_file() and not args.force:
        if not record.is_file():
            raise CliError(f"{ckpt} holds an earlier run with no record of its settings; remove it or "
                           "pass --force to start afresh")
        check_record(record, "embed", settings, ckpt)
    feat_dir = existing(args.features, "feature folder")
    scene = load_scene(args.scene, dev)
    cams = capture = open_dataset(args.data, args.skip_missing).cameras
    names = [str(c.image_name).replace("/", "_") for c in cams]
    pca = PCABasis.load(existing(str(Path(feat_dir) / "pca.pt"), "PCA file"))
    fs = FeatureSet(Path(feat_dir), names, pca)
    keep = [i for i, n in enumerate(names) if fs.path(n).is_file()]
    if not keep:
        raise SystemExit(f"tiger embed: none of the dataset's {len(names)} images has a feature map "
                         f"in {feat_dir}/features (run `tiger features` first)")
    cams = [cams[i].to(dev) if hasattr(cams[i], "to") else cams[i] for i in keep]
    summary = Summary("tiger embed")
    if Path(ckpt).is_file() and args.force:
        Path(ckpt).unlink()  # --force: start afresh
    write_record(record, "embed", settings)
    maps = lambda i: fs.load(names[keep[i]])  # noqa: E731
    # lifting reads the maps that training then keeps (one read); a checkpoint's run is resumed instead
    res = train_field(scene, cams, maps, pca=pca, checkpoint=ckpt, init=args.init, steps=args.steps,
                      coarse=args.coarse, coarse_factor=args.coarse_factor, lr=args.lr,
                      lr_final=args.lr_final, crop_pixels=args.crop_pixels, batch_views=args.batch_views,
                      loss=args.loss)
    if res.lift_seconds:
        summary.add(f"lifted in {res.lift_seconds:.1f} s")
    scene.save_ply(out)
    write_record(record, "embed", settings, finished=True,
                 results={"steps": res.steps, "full_loss": res.full_loss, "seconds": res.seconds,
                          "seconds_by_stage": res.stages})
    from tiger.scene.cameras_json import cameras_json_path, write_cameras_json

    if not cameras_json_path(out).is_file():  # `tiger render` renders along the capture's cameras
        write_cameras_json(cameras_json_path(out), capture)
    summary.add(f"{len(keep)} views, {res.steps} steps, {res.seconds:.1f} s"
                + (f"; loss over every pixel of every view {res.full_loss:.4f}" if res.full_loss is not None else ""))
    if res.stages:
        summary.add("seconds by stage: " + ", ".join(f"{k} {v:.1f}" for k, v in res.stages.items()))
    summary.add(res.coverage())
    summary.add(f"scene with language features -> {out}")
    summary.print()
    return 0
