"""Fit the real 'fox' capture (instant-ngp's 50 photographs with lens distortion, no
point cloud) and print held-out PSNR/SSIM against steps and time.

    python -m benchmarks.recon_fox                       # CPU: downscale 8, 700 steps, <= 10 min
    python -m benchmarks.recon_fox --device cuda --downscale 2 --iterations 7000 --time-budget 240
    python -m benchmarks.recon_fox --downscale 4 --mask-border --appearance
    python -m benchmarks.recon_fox --init-colors random --init-radius 0.35   # the earlier defaults

The data is looked up at ``<repo>/../shared/data/fox`` unless ``--data`` is given. Test
views are every 8th image in name order (INRIA's rule); images are undistorted once and
cached (``--cache``). The saved PLY is reloaded and compared bit for bit.
"""
from __future__ import annotations

import argparse
import json
import logging
import sys
import time
from pathlib import Path

import torch

REPO = Path(__file__).resolve().parents[1]


def main(argv: list | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", type=Path, default=REPO.parent / "shared" / "data" / "fox")
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--downscale", type=float, default=8.0)
    ap.add_argument("--iterations", type=int, default=700)
    ap.add_argument("--time-budget", type=float, default=600.0, help="seconds of training before stopping")
    ap.add_argument("--eval-every", type=int, default=500)
    ap.add_argument("--init-points", type=int, default=3000)
    ap.add_argument("--init-radius", type=float, default=1.0,
                    help="random init within this x camera distance (0.35 left parts of the views uncovered)")
    ap.add_argument("--max-gaussians", type=int, default=20_000)
    ap.add_argument("--sh-degree", type=int, default=3)
    ap.add_argument("--init-colors", choices=("random", "views"), default="views",
                    help="colours of the random initial points: their mean pixel colour (default) or random (INRIA)")
    ap.add_argument("--mask-border", action="store_true",
                    help="leave the black border of undistortion out of the loss and of PSNR/SSIM")
    ap.add_argument("--appearance", action="store_true", help="per-training-image affine colour correction")
    ap.add_argument("--threads", type=int, default=None, help="torch CPU threads")
    ap.add_argument("--cache", type=Path, default=None, help="undistorted-image cache folder")
    ap.add_argument("--out", type=Path, default=REPO / "outputs" / "recon_fox")
    ap.add_argument("--json", type=Path, default=None, help="also write the results here")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    if args.threads:
        torch.set_num_threads(args.threads)
    if not (args.data / "transforms.json").is_file():
        print(f"fox data not found at {args.data} (expected transforms.json + images/); skipping")
        return 0

    from tiger.recon import ReconConfig, Trainer, load_views
    from tiger.scene import GaussianScene
    from tiger.scene.dataset import load_dataset
    from tiger.scene.images import undistortion_valid_mask

    ds = load_dataset(args.data)
    train_raw, test_raw = ds.split(8)
    t0 = time.perf_counter()
    cache = args.cache or (args.out / "cache")
    train_c, train_i = load_views(train_raw, args.downscale, cache_dir=cache, progress=True)
    test_c, test_i = load_views(test_raw, args.downscale, cache_dir=cache, progress=True)
    masks = test_masks = None
    if args.mask_border:
        masks = [undistortion_valid_mask(c, args.downscale) for c in train_raw]
        test_masks = [undistortion_valid_mask(c, args.downscale) for c in test_raw]
    t_load = time.perf_counter() - t0
    H, W = train_i[0].shape[:2]
    cfg = ReconConfig.scaled(args.iterations, sh_degree=args.sh_degree, init_random_points=args.init_points,
                             init_radius_fraction=args.init_radius, init_colors=args.init_colors,
                             appearance=args.appearance,
                             max_gaussians=args.max_gaussians, eval_every=args.eval_every,
                             time_budget_s=args.time_budget, progress=sys.stderr.isatty())
    tr = Trainer(train_c, train_i, cfg, device=args.device, out_dir=args.out, test_cameras=test_c,
                 test_images=test_i, masks=masks, test_masks=test_masks)
    print(f"fox: {len(train_c)} train / {len(test_c)} test views at {W}x{H} (downscale {args.downscale:g}), "
          f"device {args.device}, {torch.get_num_threads()} CPU threads; images loaded+undistorted in "
          f"{t_load:.1f} s; scene extent {tr.extent:.3f}; {len(tr.scene)} initial Gaussians")
    scene = tr.fit()
    ply = args.out / "fox.ply"
    scene.save_ply(ply)
    same = GaussianScene.load_ply(ply).equal(scene.to("cpu"))

    over = " (undistorted pixels only)" if args.mask_border else ""
    print(f"\n| step | train time (s) | test PSNR{over} (dB) | test SSIM | Gaussians |")
    print("|---:|---:|---:|---:|---:|")
    for h in tr.history:
        print(f"| {h['step']} | {h['time_s']:.1f} | {h['psnr']:.2f} | {h['ssim']:.4f} | {h['gaussians']} |")
    last = tr.history[-1]
    print(f"\nfinal: step {last['step']}/{cfg.iterations}, {last['time_s']:.1f} s, PSNR {last['psnr']:.2f} dB, "
          f"SSIM {last['ssim']:.4f}, {last['gaussians']} Gaussians; saved {ply} "
          f"({'reloads identically' if same else 'RELOAD MISMATCH'})")
    if args.json:
        args.json.write_text(json.dumps({"history": tr.history, "resolution": [W, H], "device": args.device,
                                         "downscale": args.downscale, "reload_identical": same,
                                         "config": cfg.to_dict(), "mask_border": args.mask_border}, indent=1))
    return 0 if same else 1


if __name__ == "__main__":
    raise SystemExit(main())
