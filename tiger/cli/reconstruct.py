"""``tiger reconstruct``: posed images -> a 3DGS scene (INRIA's recipe)."""
from __future__ import annotations

import argparse
import json
import logging
from pathlib import Path

from .common import (CliError, Summary, add_common, add_skip_missing, claim_output, device_of, existing,
                     finish_output, open_dataset, run_settings)

log = logging.getLogger(__name__)


def add_parser(sub) -> None:
    p = sub.add_parser(
        "reconstruct", help="fit a Gaussian scene to posed images (COLMAP or transforms.json)",
        description="Fit a 3D Gaussian Splatting scene to a COLMAP model (sparse/0 + images/) or a "
                    "NeRF/instant-ngp transforms.json, with the 3DGS recipe (L1 + 0.2 D-SSIM, "
                    "densification, opacity reset, SH schedule). Every 8th image in name order is held "
                    "out (INRIA's rule; --test-every) and never trained on. Held-out PSNR, as 3DGS "
                    "reports it: per held-out view 10 log10(1 / MSE) of the saved scene's render (all SH "
                    "bands, black background, clamped to [0, 1]) against the photograph (in [0, 1]), MSE "
                    "over the counted pixels and the 3 channels; the mean over the views (SSIM likewise). "
                    "With lens distortion the black border of "
                    "undistortion is left out of the loss and of the metric (metrics.json: psnr_pixels, "
                    "psnr_definition); "
                    "random initial points take their colour from the views; training renders over a "
                    "random background colour unless images have transparency (--random-background). "
                    "Checkpoints allow --resume. Writes "
                    "OUT/scene.ply (INRIA's PLY), OUT/cameras.json (the capture's cameras, INRIA's "
                    "format; `tiger render` renders along them), OUT/metrics.json, OUT/tiger_run.json "
                    "(the settings; --resume must match them). The undistorted-image cache and the "
                    "checkpoint are removed when the run finishes (--keep-cache keeps them); a "
                    "cache left by a stopped run does not block a rerun.",
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
    p.add_argument("--max-gaussians", type=int, default=None, metavar="N",
                   help="densification never grows the scene past N Gaussians (the strongest "
                        "gradients win; default: no cap)")
    p.add_argument("--appearance", action=argparse.BooleanOptionalAction, default=False,
                   help="per-training-image affine colour correction (exposure / white balance) in the "
                        "loss; its mean over the images is moved into the scene's colours at the end, so "
                        "the saved scene and the held-out PSNR show the average appearance "
                        "(default: %(default)s)")
    p.add_argument("--random-background", action=argparse.BooleanOptionalAction, default=None,
                   help="render each training step over a random background colour, so that no "
                        "Gaussian can leave a see-through gap that the background fills in. Default: on "
                        "when no image has transparent pixels (opaque photographs), off (black) when "
                        "some do (their transparent pixels are composited over black, a colour the "
                        "renders must then learn); held-out views are always rendered over black. "
                        "metrics.json: training_background")
    p.add_argument("--time-budget", type=float, default=None, metavar="SECONDS",
                   help="stop training once it took this long (a resumed run counts its earlier "
                        "time), then evaluate and write the scene as usual (default: no budget)")
    p.add_argument("--checkpoint-every", type=int, default=1000,
                   help="steps between checkpoints (OUT/checkpoint.pt; also written at the end and "
                        "on Ctrl-C)")
    p.add_argument("--resume", action="store_true",
                   help="continue from OUT/checkpoint.pt; refused, naming what differs, when OUT holds "
                        "a reconstruction with another dataset or settings (or no record of one)")
    p.add_argument("--finetune", default=None, metavar="PLY",
                   help="start from this scene instead of initialising (e.g. after a deletion)")
    p.add_argument("--keep-cache", action="store_true",
                   help=f"keep OUT/{CACHE} (undistorted images) and OUT/checkpoint.pt after a finished "
                        "run (default: removed once scene.ply is written)")
    p.set_defaults(func=run)


CACHE = "image_cache"
#: what metrics.json's "psnr" is (INRIA's evaluation; ``psnr_pixels`` says which pixels count)
PSNR_DEFINITION = ("mean over the held-out views of 10 log10(1 / MSE), MSE over the counted pixels and the "
                   "3 channels of the saved scene's render (all SH bands, black background, clamped to "
                   "[0, 1]) against the held-out photograph (values in [0, 1]); SSIM: 11x11 Gaussian "
                   "window (sigma 1.5), mean over the same pixels, then over the views")


def _check_arguments(args: argparse.Namespace) -> None:
    """Refuse impossible numbers before anything is created."""
    if args.steps < 1:
        raise CliError(f"--steps must be >= 1, got {args.steps}")
    if not args.downscale > 0:
        raise CliError(f"--downscale must be positive, got {args.downscale}")
    if not 0 <= args.sh_degree <= 3:
        raise CliError(f"--sh-degree must be 0..3, got {args.sh_degree}")
    if args.test_every < 0 or args.checkpoint_every < 0 or args.init_points < 1:
        raise CliError("--test-every and --checkpoint-every must be >= 0 and --init-points >= 1")


def _clean_up(out: Path, keep: bool) -> list[str]:
    """After a finished run: remove the image cache and the checkpoint unless ``keep``."""
    import shutil

    if keep:
        return []
    gone = []
    if (out / CACHE).is_dir():
        shutil.rmtree(out / CACHE)
        gone.append(CACHE)
    if (out / "checkpoint.pt").is_file():
        (out / "checkpoint.pt").unlink()
        gone.append("checkpoint.pt")
    return gone


def run(args: argparse.Namespace) -> int:
    from tiger.recon import ReconConfig, Trainer, load_views
    from tiger.recon.data import masked_fraction, training_background, transparent_images, valid_pixel_masks
    from tiger.scene import GaussianScene
    from tiger.scene.cameras_json import cameras_json_path, write_cameras_json
    from tiger.train import CheckpointMismatch
    from tiger.utils.io import atomic_write

    _check_arguments(args)
    dev = device_of(args.device)
    if args.max_gaussians is not None and args.max_gaussians < 1:
        raise CliError(f"--max-gaussians must be >= 1, got {args.max_gaussians}")
    if args.time_budget is not None and not args.time_budget > 0:
        raise CliError(f"--time-budget must be > 0 seconds, got {args.time_budget}")
    data = existing(args.data, "dataset")
    ds = open_dataset(args.data, args.skip_missing)  # a bad dataset is refused before OUT exists
    # a stopped run's image cache does not block a rerun; --resume must match the run's settings
    out = claim_output(args.out, "reconstruct",
                       run_settings(args, ignore=("checkpoint_every", "keep_cache", "time_budget")),
                       force=args.force, resume=args.resume, leftovers=(CACHE,))
    summary = Summary("tiger reconstruct")
    train, test = ds.split(args.test_every)
    summary.add(f"{len(train)} training views, {len(test)} test views from {data} ({ds.kind})")
    cache = out / CACHE
    train_cams, train_imgs = load_views(train, args.downscale, cache_dir=cache, progress=True)
    test_cams, test_imgs = load_views(test, args.downscale, cache_dir=cache, progress=True)
    transparent = transparent_images([*train, *test])
    random_background, background_note = training_background(transparent, args.random_background)
    if random_background and transparent:
        log.warning("--random-background with transparent images: %s", background_note)
    summary.add(f"training background: {background_note}")
    # INRIA's 30k schedule compressed to --steps (identical at 30000).
    cfg = ReconConfig.scaled(args.steps, sh_degree=args.sh_degree,
                             init_random_points=args.init_points, max_gaussians=args.max_gaussians,
                             appearance=args.appearance, random_background=random_background,
                             time_budget_s=args.time_budget, checkpoint_every=args.checkpoint_every)
    scene = GaussianScene.load_ply(existing(args.finetune, "scene")) if args.finetune else None
    # the black border that undistortion leaves counts neither in the loss nor in the metric
    train_masks, test_masks = valid_pixel_masks(train, args.downscale), valid_pixel_masks(test, args.downscale)
    trainer = Trainer(train_cams, [im.to(dev) for im in train_imgs], cfg, scene=scene,
                      init_points=ds.points, init_colors=ds.point_colors, device=dev, out_dir=out,
                      test_cameras=test_cams, test_images=[im.to(dev) for im in test_imgs],
                      masks=train_masks, test_masks=test_masks)
    ckpt = out / "checkpoint.pt"
    if args.resume and ckpt.is_file():
        try:
            trainer.load(ckpt)
        except CheckpointMismatch as exc:
            raise CliError(f"--resume: {exc}") from None
        summary.add(f"resumed from {ckpt} at step {trainer.step}")
    try:
        scene = trainer.fit()
    except KeyboardInterrupt:
        held = (f"{ckpt} holds step {trainer.checkpoint_step}: continue with --resume"
                if trainer.checkpoint_step is not None else "this run wrote no checkpoint yet")
        raise KeyboardInterrupt(f"stopped at step {trainer.step} of {cfg.iterations}; {held}") from None
    if trainer.outcome is not None and trainer.outcome.stopped == "time budget":
        summary.add(f"time budget of {args.time_budget:g} s reached: stopped at step {trainer.step} of "
                    f"{cfg.iterations} (--resume with a larger --time-budget continues)")
    scene.save_ply(out / "scene.ply")
    write_cameras_json(cameras_json_path(out / "scene.ply"), ds.cameras)
    summary.add(f"scene: {len(scene)} Gaussians -> {out / 'scene.ply'} (cameras: {out / 'cameras.json'})")
    metrics = {"gaussians": len(scene), "steps": trainer.step, "seconds": trainer.elapsed,
               "stopped": trainer.outcome.stopped if trainer.outcome is not None else "done",
               "training_background": background_note}
    if test_cams:
        ev = trainer.evaluate()
        metrics.update({k: v for k, v in ev.items() if isinstance(v, (int, float))})
        metrics["psnr_definition"] = PSNR_DEFINITION
        metrics["psnr_pixels"] = ("all pixels of the held-out views" if test_masks is None else
                                  f"held-out pixels inside the undistorted image ({100 * masked_fraction(test_masks):.1f} % "
                                  "black undistortion border left out, as in the training loss)")
        summary.add(f"test views: PSNR {ev.get('psnr', float('nan')):.2f} dB, "
                    f"SSIM {ev.get('ssim', float('nan')):.4f} ({metrics['psnr_pixels']})")
    with atomic_write(out / "metrics.json", "w") as fh:
        json.dump(metrics, fh, indent=2)
    gone = _clean_up(out, args.keep_cache)
    if gone:
        summary.add(f"removed {', '.join(gone)} (--keep-cache keeps them)")
    finish_output(out, "reconstruct")
    summary.print()
    return 0
