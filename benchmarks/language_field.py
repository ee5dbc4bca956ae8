"""Language field training: time per step and to convergence, features-only vs full backward.

(1) Per-step time on the standard scene (N Gaussians, one W x W view, 64-d features): render L,
    L1 loss against a target map, backward, Adam step on L. "features-only": only L requires grad
    (the rasterizer's features-only backward, what train_field does); "full": the geometry
    (means, quats, scales, opacities) requires grad too, so the full backward runs (and its
    gradients are thrown away). Error column: relative error of the float32 L gradient against
    float64 ("-" where N x W^2 is too large for the float64 run).
(2) Convergence on the synthetic labelled scene (tiger.testing.labelled_scene): train_field from
    random L; at milestones, time, loss and the worst per-label retrieval precision / recall
    (cosine score, automatic threshold); "converged" = loss within 10 % of the last milestone's.
    The full backward follows the same trajectory (only L is updated), so its time to
    convergence is the features-only time x the per-step ratio of table (1).

(3) ``train_field`` as ``tiger embed`` runs it: V float16 64-d maps of H x W written to disk in
    ``tiger features``' layout and read through ``FeatureSet.load`` (once), N Gaussians of the
    synthetic labelled scene, maps = renders of their label embeddings at the map size plus smooth
    per-view noise (``--loop-noise``: real maps disagree between views, so no field fits them
    exactly). Rows: lifting only, the defaults (lift, then training), and the earlier default
    (10,000 steps of whole views at a constant lr 2.5e-3, from the same lifted start;
    ``--loop-reference-steps 0`` skips it). Per row: wall time of the call and its stages (reading
    the maps, lifting, training), the loss over every valid pixel of every view at the end, and
    the worst label's retrieval precision / recall. The defaults on CUDA are the fox's size (43
    views of 1080x1920, 250k Gaussians).

    python -m benchmarks.language_field                 # CPU
    python -m benchmarks.language_field --device cuda   # GPU (needs the CUDA rasterizer)
    # tiger embed's defaults at the fox's size, against 10,000 steps of the earlier default:
    python -m benchmarks.language_field --device cuda --only loop
"""
from __future__ import annotations

import argparse
from pathlib import Path
from typing import Optional, Sequence

import torch

from benchmarks.common import median_time, print_table, rel_err  # noqa: E402
from tests.render.standard_scenes import standard_view  # noqa: E402

import tiger  # noqa: E402


def step_fn(sc, target, lang, opt, full: bool):
    geo = [t.detach().requires_grad_(full) for t in (sc.means, sc.quats, sc.scales, sc.opacities)]

    def step():
        opt.zero_grad(set_to_none=True)
        for t in geo:
            t.grad = None
        out = tiger.rasterize_gaussians(*geo, lang, sc.viewmat, sc.K, sc.width, sc.height, check_finite=False)
        (out["color"] - target).abs().mean().backward()
        opt.step()

    return step


def grad_error(sc64, target64) -> float:
    """Relative error of the float32 gradient of L against float64 (features-only backward)."""
    grads = {}
    for dt in (torch.float64, torch.float32):
        s = sc64.to(dtype=dt)
        lang = (0.5 * s.features).detach().clone().requires_grad_(True)  # away from the optimum
        out = tiger.rasterize_gaussians(s.means, s.quats, s.scales, s.opacities, lang, s.viewmat, s.K,
                                        s.width, s.height, check_finite=False)
        ((out["color"] - target64.to(dt)) ** 2).mean().backward()
        grads[dt] = lang.grad
    return rel_err(grads[torch.float32], grads[torch.float64])


def per_step(device: str, cases: list[tuple[int, int]]) -> list[dict]:
    cuda = device == "cuda"
    rows = []
    for n, w in cases:
        sc = standard_view(n, w, w, seed=1).to(device=device)
        with torch.no_grad():
            target = tiger.rasterize_gaussians(sc.means, sc.quats, sc.scales, sc.opacities, sc.features,
                                               sc.viewmat, sc.K, w, w)["color"]
        times = {}
        for full in (False, True):
            lang = (0.1 * torch.randn(n, 64, device=device)).requires_grad_(True)
            opt = torch.optim.Adam([lang], lr=1e-2)
            # GPU: enough warm-up that the caching allocator and CUB's scratch have settled
            # (with one warm-up call, whichever variant ran first paid for them).
            times[full] = median_time(step_fn(sc, target, lang, opt, full), repeats=20 if cuda else 5,
                                      warmup=5 if cuda else 1, cuda=cuda)
        err = grad_error(standard_view(n, w, w, seed=1).to(device=device, dtype=torch.float64),
                         target.double()) if n * w * w <= (2e11 if cuda else 2e9) else "-"  # float64 copy too large
        rows.append({"N": n, "W=H": w, "features_only_ms": 1e3 * times[False], "full_ms": 1e3 * times[True],
                     "full/features": times[True] / times[False], "grad_rel_err_f32": err})
    return rows


def convergence(device: str, steps: int, lr: float = 0.05) -> list[dict]:
    """Milestones every steps/10 of one train_field run (continued through checkpoint/resume, which
    is identical to one run): time, loss (mean of the last 10 steps) and the worst precision and
    recall over the labels (cosine score, automatic threshold)."""
    import logging
    import tempfile

    from tiger.language.field import train_field
    from tiger.retrieval import retrieve
    from tiger.testing.labelled_scene import make_labelled_scene, oracle_feature_maps

    logging.getLogger("tiger.language.field").setLevel(logging.ERROR)
    ls = make_labelled_scene(per_object=80, floor=400, views=12, size=96)
    maps = [(f.to(device), v.to(device)) for f, v in oracle_feature_maps(ls)]  # rendered on the CPU
    s = ls.scene.to(device)
    labels = ls.labelled.labels.to(device)
    ls.cameras = [c.to(device) for c in ls.cameras]
    rows, seconds = [], 0.0
    every = max(10, steps // 10)
    with tempfile.TemporaryDirectory() as tmp:
        ck = Path(tmp) / "field.ckpt"
        for milestone in range(every, steps + 1, every):
            r = train_field(s, ls.cameras, maps, steps=milestone, lr=lr, batch_views=2, progress=False,
                            checkpoint=ck, checkpoint_every=0)
            seconds += r.seconds
            prec, rec = [], []
            for i, name in enumerate(ls.labelled.names):
                rr = retrieve(s, name, encoder=ls.encoder)
                gt = labels == i
                tp = int((rr.mask & gt).sum())
                prec.append(tp / max(rr.count, 1))
                rec.append(tp / int(gt.sum()))
            rows.append({"N": len(labels), "views": len(ls.cameras), "W=H": 96, "lr": lr, "step": milestone,
                         "seconds": seconds, "loss": sum(r.losses[-10:]) / len(r.losses[-10:]),
                         "min_precision": min(prec), "min_recall": min(rec)})
    final = rows[-1]["loss"]
    conv = next(r for r in rows if r["loss"] <= 1.1 * final)
    print(f"# converged (loss within 10 % of step {steps}'s) at step {conv['step']}, {conv['seconds']:.1f} s")
    return rows


def _smooth_noise(h: int, w: int, dim: int, sigma: float, gen: torch.Generator, device: str) -> torch.Tensor:
    """[H, W, D] noise of std ``sigma`` per channel, smooth over ~16 px (bilinear from a coarse grid):
    the view-to-view disagreement of real feature maps, which no field can fit exactly."""
    coarse = torch.randn(1, dim, h // 16 + 2, w // 16 + 2, generator=gen).to(device)
    return sigma * torch.nn.functional.interpolate(coarse, size=(h, w), mode="bilinear",
                                                   align_corners=False)[0].permute(1, 2, 0)


def loop_scene(device: str, views: int, height: int, width: int, gaussians: int, noise: float, tmp: Path):
    """The synthetic labelled scene with ``gaussians`` Gaussians and V float16 maps of H x W written
    in ``tiger features``' layout under ``tmp``: renders of the label embeddings plus smooth noise."""
    from tiger.language.extract import FeatureSet
    from tiger.testing.labelled_scene import DEFAULT_LABELS, make_labelled_scene

    k = len(DEFAULT_LABELS)
    per_object = max(1, gaussians // (2 * k))
    ls = make_labelled_scene(per_object=per_object, floor=max(1, gaussians - k * per_object), views=views,
                             size=64)
    ls.labelled.scene = ls.scene.to(device)
    ls.labelled.labels = ls.labelled.labels.to(device)
    cams = [c.to(device) for c in ls.cameras]
    lang = ls.label_lang.to(device)[ls.labelled.labels]
    names = [f"view{i:03d}" for i in range(views)]
    gen = torch.Generator().manual_seed(0)
    (tmp / "features").mkdir()
    with torch.no_grad():
        for name, cam in zip(names, cams):
            out = ls.scene.render(cam.resized(width, height), lang)
            feats = out["color"]
            if noise:
                feats += _smooth_noise(height, width, feats.shape[2], noise, gen, device)
            torch.save({"features": feats.half().cpu(), "valid": (out["alpha"] >= 0.5).cpu()},
                       tmp / "features" / f"{name}.pt")
    fs = FeatureSet(tmp, names, None)
    return ls, cams, (lambda i: fs.load(names[i]))


def worst_precision_recall(ls) -> tuple[float, float]:
    """The worst label's precision and recall of ``retrieve`` (cosine score, automatic threshold)."""
    from tiger.retrieval import retrieve

    prec, rec = [], []
    for i, name in enumerate(ls.labelled.names):
        rr = retrieve(ls.scene, name, encoder=ls.encoder)
        gt = ls.labelled.labels == i
        tp = int((rr.mask & gt).sum())
        prec.append(tp / max(rr.count, 1))
        rec.append(tp / int(gt.sum()))
    return min(prec), min(rec)


def parse_overrides(text: str) -> dict:
    """``"coarse_factor=4,steps=3000"`` -> FieldConfig overrides (ints, floats or strings)."""
    out = {}
    for item in filter(None, text.split(",")):
        key, _, value = item.partition("=")
        for cast in (int, float, str):
            try:
                out[key.strip()] = cast(value)
                break
            except ValueError:
                continue
    return out


def train_loop(device: str, views: int, height: int, width: int, gaussians: int, steps: Optional[int],
               reference_steps: int, noise: float, extra: Sequence[str] = ()) -> list[dict]:
    """``train_field`` as ``tiger embed`` runs it at its defaults on maps read from disk (lifting,
    training, the loss over every pixel of every view), against the earlier default from the same
    lifted start (module docstring, 3)."""
    import copy
    import logging
    import tempfile

    from tiger.language.field import FieldConfig, train_field

    logging.getLogger("tiger.language.field").setLevel(logging.ERROR)
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        ls, cams, load = loop_scene(device, views, height, width, gaussians, noise, Path(tmp))
        start = copy.deepcopy(ls.scene)
        base = {"progress": False, **({"steps": steps} if steps is not None else {})}
        configs = [("lift only", FieldConfig(**{**base, "steps": 0})), ("defaults", FieldConfig(**base))]
        for text in extra:
            configs.append((text, FieldConfig(**{**base, **parse_overrides(text)})))
        if reference_steps:
            configs.append(("before (whole views, lr 2.5e-3)",
                            FieldConfig.before_lift(steps=reference_steps, progress=False)))
        # warm-up (first-call costs: kernels' set-up, allocator, lazy imports), not reported
        train_field(copy.deepcopy(start), cams[:2], lambda i: load(i), steps=3, coarse=0.34, progress=False)
        for name, cfg in configs:
            ls.labelled.scene = copy.deepcopy(start)
            if device == "cuda":
                torch.cuda.synchronize()
            r = train_field(ls.scene, cams, load, config=cfg)
            p, rc = worst_precision_recall(ls)
            st = r.stages
            rows.append({"run": name, "N": len(ls.scene), "views": views, "map": f"{height}x{width}x64 f16",
                         "steps": r.steps, "crop_px": cfg.crop_pixels, "seconds": r.seconds,
                         "read_s": st.get("read maps", 0.0), "lift_s": st.get("lift", 0.0),
                         "train_s": st.get("train", 0.0), "ms/step": 1e3 * st.get("train", 0.0) / r.steps if r.steps else "-",
                         "full_loss": r.full_loss, "min_P": p, "min_R": rc})
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--device", default="cpu", choices=("cpu", "cuda"))
    ap.add_argument("--steps", type=int, default=200)
    ap.add_argument("--only", choices=("step", "convergence", "loop"), default=None, help="run one table only")
    ap.add_argument("--loop-views", type=int, default=None, help="default: 43 on CUDA (the fox), 6 on the CPU")
    ap.add_argument("--loop-size", type=int, nargs=2, default=None, metavar=("H", "W"),
                    help="map size (default: 1080 1920 on CUDA, 96 160 on the CPU)")
    ap.add_argument("--loop-gaussians", type=int, default=None, help="default: 250000 on CUDA, 4000 on the CPU")
    ap.add_argument("--loop-steps", type=int, default=None, help="training steps (default: tiger embed's)")
    ap.add_argument("--loop-reference-steps", type=int, default=10_000,
                    help="steps of the earlier default (whole views, constant lr 2.5e-3) to compare with "
                         "(default 10000; 0 skips this slow run)")
    ap.add_argument("--loop-extra", action="append", default=[], metavar="K=V,...",
                    help="one more row: the defaults with these FieldConfig fields changed, e.g. "
                         "'coarse_factor=4,coarse=0.9,steps=3000' (repeatable)")
    ap.add_argument("--loop-noise", type=float, default=0.05,
                    help="std of the smooth per-view noise added to the maps (default 0.05; 0: exact renders)")
    args = ap.parse_args()
    cuda = args.device == "cuda"
    views = args.loop_views or (43 if cuda else 6)
    size = args.loop_size or ((1080, 1920) if cuda else (96, 160))
    gaussians = args.loop_gaussians or (250_000 if cuda else 4000)
    if args.device == "cuda":
        if not torch.cuda.is_available():
            raise SystemExit("benchmarks/language_field.py: no CUDA device")
        try:
            sc = standard_view(10, 16, 16).to(device="cuda")
            tiger.rasterize_gaussians(sc.means, sc.quats, sc.scales, sc.opacities, sc.features, sc.viewmat, sc.K, 16, 16)
        except (RuntimeError, NotImplementedError) as exc:
            print(f"SKIPPED: the rasterizer has no CUDA kernels in this build ({str(exc).splitlines()[0]})")
            return
    cases = [(100_000, 256), (1_000_000, 512)] if args.device == "cuda" else [(5_000, 64), (20_000, 128)]
    if args.only in (None, "step"):
        print_table(per_step(args.device, cases),
                    title=f"language field step (render 64-d + L1 + backward + Adam), {args.device}")
    if args.only in (None, "convergence"):
        print_table(convergence(args.device, args.steps),
                    title=f"language field convergence, synthetic labelled scene, {args.device}")
    if args.only in (None, "loop"):
        print_table(train_loop(args.device, views, *size, gaussians, args.loop_steps, args.loop_reference_steps,
                               args.loop_noise, args.loop_extra),
                    title=f"train_field as tiger embed runs it (maps read from disk once, lifted, trained), "
                          f"{args.device}; full_loss: every valid pixel of every view")


if __name__ == "__main__":
    main()
