"""Pool or fresh views: how well an edit reaches a known answer with each camera-sampling mode.

The analytic guidance (:class:`tiger.testing.ideal_denoiser.IdealDenoiserGuidance`) pulls every
render toward the render of a ground-truth edit (the ball of the demo tabletop recoloured red), so
the edit's error is measurable. For each step count and each mode (``--pools``: 0 = fresh cameras
every step, K = a pool of K camera sets, :attr:`tiger.edit.EditConfig.view_pool`) the edit runs
from scratch with the edit's own settings (densification schedule scaled to the step count) and is
measured from evaluation cameras the loop never draws: ``--eval-views`` azimuths at each of
three elevations (the low end, middle and high end of the edit's elevation range, inset by 2°).

Columns: object PSNR (renders of the edited scene vs the ground truth on the object's pixels,
footprint > 0.5, in dB), its worst view, locality PSNR (outside the object, tiger.eval.edit.locality)
and seconds per step on this machine. Means over ``--seeds`` (view sampler and guidance noise).

    python -m benchmarks.edit_view_pool --steps 100 300 1200 --pools 0 16 64 256 --size 48 --density 0.25
"""
from __future__ import annotations

import argparse
import json
import math
import time
from pathlib import Path

import torch

from benchmarks.common import print_table
from benchmarks.edit import RED, demo_scene
from tiger.edit import EditConfig, edit, resolve_target
from tiger.edit.views import ObjectViews
from tiger.eval.edit import locality
from tiger.scene import render_rgb
from tiger.scene.sh import rgb_to_sh
from tiger.testing.ideal_denoiser import IdealDenoiserGuidance, render_targets


def evaluation_cameras(tgt, cfg: EditConfig, n_azimuths: int) -> list:
    """``n_azimuths`` evenly spaced azimuths (offset by half a step from the fixed ring) at three
    elevations spanning the edit's range: cameras an edit's sampler draws with probability 0."""
    views = ObjectViews(tgt.center, tgt.bbox_min, tgt.bbox_max, force_360=True, width=cfg.width,
                        height=cfg.height, fov_deg=cfg.fov_deg, elevation_deg=cfg.elevation_deg, fill=cfg.fill)
    lo, hi = cfg.elevation_deg
    az = (torch.arange(n_azimuths, dtype=torch.float64) + 0.5) * (2 * math.pi / n_azimuths)
    cams = []
    for e in (lo + 2.0, 0.5 * (lo + hi), hi - 2.0):
        cams += views.cameras_at(az, torch.full((n_azimuths,), math.radians(e), dtype=torch.float64))
    return cams


def object_psnr(edited, weights_after, truth, mask, cams, background) -> tuple[float, float]:
    """(PSNR over all object pixels of ``cams``, the worst single view's), dB."""
    got, _ = render_rgb(edited, cams, background, footprint=weights_after > 0)
    want, foot = render_rgb(truth, cams, background, footprint=mask)
    err = (got.clamp(0, 1) - want.clamp(0, 1)).square().mean(-1)
    obj = foot > 0.5
    total = float(err[obj].mean())
    per_view = [float(err[v][obj[v]].mean()) for v in range(len(cams)) if bool(obj[v].any())]
    db = lambda m: -10 * math.log10(max(m, 1e-12))  # noqa: E731
    return db(total), db(max(per_view))


def run(args) -> list[dict]:
    scene, query = demo_scene(args.density, "cpu")
    tgt = resolve_target(scene, query, tau=0.5)
    truth = scene.clone()
    truth.sh_dc[tgt.mask] = rgb_to_sh(torch.tensor(RED)).expand(tgt.count, 3)
    truth.sh_rest[tgt.mask] = 0
    white = torch.ones(3)
    rows = []
    for steps in args.steps:
        for pool in args.pools:
            acc = []
            for seed in args.seeds:
                cfg = EditConfig(steps=steps, width=args.size, height=args.size, seed=seed, view_pool=pool,
                                 lrs={"sh_dc": args.lr_color}, background=(1.0, 1.0, 1.0), progress=False,
                                 checkpoint_every=0, densify_every=max(1, steps // 12), densify_from=max(1, steps // 12))
                guide = IdealDenoiserGuidance(render_targets(truth, white), seed=seed)
                t0 = time.perf_counter()
                res = edit(scene, tgt, guide, config=cfg)
                dt = time.perf_counter() - t0
                cams = evaluation_cameras(tgt, cfg, args.eval_views)
                psnr, worst = object_psnr(res.scene, res.weights, truth, tgt.mask, cams, white)
                loc = locality(scene, res.scene, cams, tgt.mask, res.editable, background=white)["psnr"]
                acc.append({"object_PSNR_dB": psnr, "worst_view_dB": worst, "locality_dB": loc,
                            "s_per_step": dt / steps, "gaussians_after": len(res.scene)})
                print(json.dumps({"steps": steps, "pool": pool, "seed": seed, **acc[-1]}), flush=True)
            row = {"steps": steps, "mode": "fresh" if pool == 0 else f"pool {pool}", "seeds": len(acc)}
            for k in acc[0]:
                row[k] = sum(a[k] for a in acc) / len(acc)
            row["object_PSNR_min_dB"] = min(a["object_PSNR_dB"] for a in acc)
            rows.append(row)
    return rows


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--density", type=float, default=0.25, help="demo scene density (1 = ~20k Gaussians)")
    p.add_argument("--size", type=int, default=48, help="edit render size (square, px)")
    p.add_argument("--steps", type=int, nargs="+", default=[100, 300, 1200])
    p.add_argument("--pools", type=int, nargs="+", default=[0, 16, 64, 256], help="0 = fresh cameras every step")
    p.add_argument("--seeds", type=int, nargs="+", default=[0, 1])
    p.add_argument("--eval-views", type=int, default=8, help="evaluation azimuths per elevation (3 elevations)")
    p.add_argument("--lr-color", type=float, default=0.05)
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--json", default=None, help="also write the rows here")
    args = p.parse_args()
    torch.set_num_threads(args.threads)
    rows = run(args)
    if args.json:
        Path(args.json).parent.mkdir(parents=True, exist_ok=True)
        Path(args.json).write_text(json.dumps(rows, indent=2))
    print_table(rows, "pool or fresh views: analytic edit vs its known answer (dB), CPU s/step")


if __name__ == "__main__":
    main()
