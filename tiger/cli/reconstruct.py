"""``tiger reconstruct``: posed images -> a 3DGS scene (INRIA's recipe)."""
from __future__ import annotations

import argparse
import json


from .common import (Summary, add_common, add_skip_missing, claim_output, device_of, existing, finish_output,
                     open_dataset, run_settings)


def add_parser(sub) -> None:
    p = sub.add_parser(
        "reconstruct", help="fit a Gaussian scene to posed images (COLMAP or transforms.json)",
        description="Fit a 3D Gaussian Splatting scene to a COLMAP model (sparse/0 + images/) or a "
                    "NeRF/instant-ngp transforms.json, with the 3DGS recipe (L1 + 0.2 D-SSIM, "
                    "densification, opacity reset, SH schedule). Every 8th image is held out; "
                    "test PSNR/SSIM are printed at the end. Checkpoints allow --resume. Writes "
                    "OUT/scene.ply (INRIA's PLY), OUT/cameras.json (the capture's cameras, INRIA's "
                    "format; `tiger render` renders along them), OUT/metrics.json.",
        epilog="example: tiger reconstruct ../shared/data/fox --out outputs/fox --steps 7000 "
               "--downscale 4",
        formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("data", help="dataset folder (COLMAP or with transforms.json) or a transforms file")
    add_common(p)
    p.add_argument("--steps", type=int, default=30_000, help="iterations (default: %(default)s)")
    p.add_argument("--downscale", type=float, default=1.0, help="image downscale factor")
    p.add_argument("--sh-degree", type=int, default=3)
    p.add_argument("--test-every", type=int, default=8, help="hold out every N-th image (0: none)")
    add_skip_missing(p)
    p.add_argument("--init-points", type=int, default=100_000,
                   help="random initial Gaussians when the dataset has no points")
    p.add_argument("--checkpoint-every", type=int, default=1000)
    p.add_argument("--resume", action="store_true",
                   help="continue from OUT/checkpoint.pt; refused, naming what differs, when OUT holds "
                        "a reconstruction with another dataset or settings (or no record of one)")
    p.add_argument("--finetune", default=None, metavar="PLY",
                   help="start from this scene instead of initialising (e.g. after a deletion)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from tiger.recon import ReconConfig, Trainer, load_views
    from tiger.scene import GaussianScene
    from tiger.scene.cameras_json import cameras_json_path, write_cameras_json
    from tiger.utils.io import atomic_write

    dev = device_of(args.device)
    data = existing(args.data, "dataset")
    out = claim_output(args.out, "reconstruct", run_settings(args, ignore=("checkpoint_every",)),
                       force=args.force, resume=args.resume)
    summary = Summary("tiger reconstruct")
    ds = open_dataset(args.data, args.skip_missing)
    train, test = ds.split(args.test_every)
    summary.add(f"{len(train)} training views, {len(test)} test views from {data} ({ds.kind})")
    cache = out / "image_cache"
    train_cams, train_imgs = load_views(train, args.downscale, cache_dir=cache, progress=True)
    test_cams, test_imgs = load_views(test, args.downscale, cache_dir=cache, progress=True)
    # INRIA's 30k schedule compressed to --steps (identical at 30000).
    cfg = ReconConfig.scaled(args.steps, sh_degree=args.sh_degree,
                             init_random_points=args.init_points,
                             checkpoint_every=args.checkpoint_every)
    scene = GaussianScene.load_ply(existing(args.finetune, "scene")) if args.finetune else None
    trainer = Trainer(train_cams, [im.to(dev) for im in train_imgs], cfg, scene=scene,
                      init_points=ds.points, init_colors=ds.point_colors, device=dev, out_dir=out,
                      test_cameras=test_cams, test_images=[im.to(dev) for im in test_imgs])
    ckpt = out / "checkpoint.pt"
    if args.resume and ckpt.is_file():
        trainer.load(ckpt)
        summary.add(f"resumed from {ckpt} at step {trainer.step}")
    try:
        scene = trainer.fit()
    except KeyboardInterrupt:
        held = (f"{ckpt} holds step {trainer.checkpoint_step}: continue with --resume"
                if trainer.checkpoint_step is not None else "this run wrote no checkpoint yet")
        raise KeyboardInterrupt(f"stopped at step {trainer.step} of {cfg.iterations}; {held}") from None
    scene.save_ply(out / "scene.ply")
    write_cameras_json(cameras_json_path(out / "scene.ply"), ds.cameras)
    summary.add(f"scene: {len(scene)} Gaussians -> {out / 'scene.ply'} (cameras: {out / 'cameras.json'})")
    metrics = {"gaussians": len(scene), "steps": trainer.step, "seconds": trainer.elapsed}
    if test_cams:
        ev = trainer.evaluate()
        metrics.update({k: v for k, v in ev.items() if isinstance(v, (int, float))})
        summary.add(f"test views: PSNR {ev.get('psnr', float('nan')):.2f} dB, "
                    f"SSIM {ev.get('ssim', float('nan')):.4f}")
    with atomic_write(out / "metrics.json", "w") as fh:
        json.dump(metrics, fh, indent=2)
    finish_output(out, "reconstruct")
    summary.print()
    return 0
