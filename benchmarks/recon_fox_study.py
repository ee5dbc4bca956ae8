"""Why does the fox's held-out PSNR plateau? One training run per hypothesis, same views.

    python -m benchmarks.recon_fox_study --downscale 4 --variants base,mask,appearance
    python -m benchmarks.recon_fox_study --device cuda --downscale 4 --variants all

Every run starts from ``benchmarks/recon_fox.py``'s settings (random init of 3000 points
within 0.35 x the camera distance, at most 20k Gaussians, SH degree 3, INRIA's schedule
compressed to ``--iterations``) and changes one thing. Per run it reports the held-out
PSNR over the whole image (the benchmark's number), over the pixels that undistortion
filled (``valid``), after the best per-image affine colour map (``cc``, a diagnostic of
exposure / white balance), the training-view PSNR (over-fitting), SSIM and the count.
A picture (ground truth, then one column per run; two held-out views) goes to ``--out``.
"""
from __future__ import annotations

import argparse
import json
import logging
import time
from pathlib import Path

import torch

REPO = Path(__file__).resolve().parents[1]

# name -> (ReconConfig overrides, mask the undistortion border, iterations factor)
VARIANTS: dict[str, tuple[dict, bool, float]] = {
    "base": ({}, False, 1.0),
    "mask": ({}, True, 1.0),
    "appearance": ({"appearance": True}, False, 1.0),
    "init_colors": ({"init_colors": "views"}, False, 1.0),
    "init_wide": ({"init_radius_fraction": 1.0}, False, 1.0),
    "init_colors_wide": ({"init_colors": "views", "init_radius_fraction": 1.0}, False, 1.0),
    "init_dense": ({"init_random_points": 20_000, "init_radius_fraction": 1.0}, False, 1.0),
    "no_reset": ({"opacity_reset_interval": 0}, False, 1.0),
    "sh1": ({"sh_degree": 1}, False, 1.0),
    "more_gaussians": ({"max_gaussians": 200_000}, False, 1.0),
    "long": ({}, False, 4.0),
    "combined": ({"init_colors": "views", "init_radius_fraction": 1.0, "appearance": True}, True, 1.0),
}


def _cc_psnr(render: torch.Tensor, target: torch.Tensor, mask: torch.Tensor) -> float:
    from tiger.recon import psnr
    from tiger.recon.appearance import fit_affine_colour

    return psnr(fit_affine_colour(render, target, mask), target, mask)


@torch.no_grad()
def measure(tr, cams, imgs, masks) -> dict:
    from tiger.recon import psnr

    scene = tr.scene.detach()
    bg = torch.tensor(tr.cfg.background, dtype=torch.float32, device=tr.device)
    full, valid, cc, renders = [], [], [], []
    for cam, img, m in zip(cams, imgs, masks):
        out = scene.render(cam, background=bg, check_finite=False)["color"].clamp(0, 1)
        full.append(psnr(out, img))
        valid.append(psnr(out, img, m))
        cc.append(_cc_psnr(out, img, m))
        renders.append(out.cpu())
    n = len(cams)
    return {"psnr": sum(full) / n, "psnr_valid": sum(valid) / n, "psnr_cc": sum(cc) / n, "renders": renders}


def save_picture(path: Path, rows: list, labels: list) -> None:
    """Rows of [H, W, 3] images side by side, one row per entry (first column ground truth)."""
    from PIL import Image, ImageDraw

    from tiger.utils.io import atomic_write

    tiles = [torch.cat(r, 1) for r in rows]
    img = torch.cat(tiles, 0)
    arr = (img.clamp(0, 1) * 255 + 0.5).to(torch.uint8).numpy()
    pic = Image.fromarray(arr)
    d = ImageDraw.Draw(pic)
    w = rows[0][0].shape[1]
    for j, lab in enumerate(labels):
        d.text((j * w + 4, 4), lab, fill=(255, 255, 0))
    with atomic_write(path, "wb") as fh:
        pic.save(fh, format="PNG")


def main(argv: list | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", type=Path, default=REPO.parent / "shared" / "data" / "fox")
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--downscale", type=float, default=4.0)
    ap.add_argument("--iterations", type=int, default=2000, help="base schedule length")
    ap.add_argument("--variants", default="base,mask,appearance", help="comma list, or 'all': " + ", ".join(VARIANTS))
    ap.add_argument("--time-budget", type=float, default=None, help="seconds of training per run")
    ap.add_argument("--eval-every", type=int, default=0)
    ap.add_argument("--cache", type=Path, default=None)
    ap.add_argument("--out", type=Path, default=REPO / "outputs" / "recon_fox_study")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    names = list(VARIANTS) if args.variants == "all" else args.variants.split(",")
    unknown = [n for n in names if n not in VARIANTS]
    if unknown:
        ap.error(f"unknown variants {unknown}; known: {list(VARIANTS)}")
    if not (args.data / "transforms.json").is_file():
        print(f"fox data not found at {args.data}; skipping")
        return 0

    from tiger.recon import ReconConfig, Trainer, load_views
    from tiger.scene.dataset import load_dataset
    from tiger.scene.images import undistortion_valid_mask

    args.out.mkdir(parents=True, exist_ok=True)
    ds = load_dataset(args.data)
    train_raw, test_raw = ds.split(8)
    cache = args.cache or (args.out / "cache")
    train_c, train_i = load_views(train_raw, args.downscale, cache_dir=cache)
    test_c, test_i = load_views(test_raw, args.downscale, cache_dir=cache)
    train_m = [undistortion_valid_mask(c, args.downscale) for c in train_raw]
    test_m = [undistortion_valid_mask(c, args.downscale) for c in test_raw]
    dev = torch.device(args.device)
    H, W = train_i[0].shape[:2]
    print(f"fox study: {len(train_c)} train / {len(test_c)} test views at {W}x{H}, device {args.device}, "
          f"{torch.get_num_threads()} threads; border (invalid) pixels: "
          f"{100 * float(sum((~m).sum() for m in test_m)) / (len(test_m) * H * W):.2f} %")
    probe = list(range(0, len(train_c), max(1, len(train_c) // 6)))[:6]
    results, pics = [], {}
    print("\n| run | steps | train s | test PSNR | test PSNR valid px | colour-corrected | train PSNR | SSIM | Gaussians |")
    print("|---|---:|---:|---:|---:|---:|---:|---:|---:|")
    for name in names:
        over, use_mask, factor = VARIANTS[name]
        iters = int(round(args.iterations * factor))
        cfg = ReconConfig.scaled(iters, **{**dict(sh_degree=3, init_random_points=3000, init_radius_fraction=0.35,
                                                  max_gaussians=20_000, progress=False,
                                                  time_budget_s=args.time_budget, eval_every=args.eval_every),
                                           **over})
        tr = Trainer(train_c, [im.to(dev) for im in train_i], cfg, device=dev, test_cameras=test_c,
                     test_images=[im.to(dev) for im in test_i],
                     masks=[m.to(dev) for m in train_m] if use_mask else None)
        t0 = time.perf_counter()
        tr.fit()
        wall = time.perf_counter() - t0
        m = measure(tr, test_c, [im.to(dev) for im in test_i], [x.to(dev) for x in test_m])
        tm = tr.evaluate([train_c[i] for i in probe], [train_i[i] for i in probe], [train_m[i] for i in probe])
        ev = tr.evaluate(masks=[x.to(dev) for x in test_m])
        pics[name] = m.pop("renders")
        row = {"run": name, "steps": tr.step, "iterations": iters, "train_s": round(tr.elapsed, 1),
               "wall_s": round(wall, 1), "overrides": over, "mask_border": use_mask, **m,
               "ssim_valid": ev["ssim"], "train_psnr_valid": tm["psnr"], "gaussians": len(tr.scene),
               "history": tr.history}
        results.append(row)
        print(f"| {name} | {tr.step}/{iters} | {tr.elapsed:.0f} | {m['psnr']:.2f} | {m['psnr_valid']:.2f} | "
              f"{m['psnr_cc']:.2f} | {tm['psnr']:.2f} | {ev['ssim']:.4f} | {len(tr.scene)} |", flush=True)
        (args.out / "fox_study.json").write_text(json.dumps(
            {"resolution": [W, H], "device": args.device, "downscale": args.downscale, "runs": results}, indent=1))
        views = [0, len(test_c) // 2]
        save_picture(args.out / "fox_study.png", [[test_i[v]] + [pics[r["run"]][v] for r in results] for v in views],
                     ["ground truth"] + [f"{r['run']} {r['psnr']:.1f} dB" for r in results])
    best = max(results, key=lambda r: r["psnr"])
    print(f"\nbest: {best['run']} {best['psnr']:.2f} dB (valid pixels {best['psnr_valid']:.2f}); picture "
          f"{args.out / 'fox_study.png'} (ground truth, then one column per run)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
