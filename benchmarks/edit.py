"""The edit loop: total time, per-step breakdown and quality of a full edit.

Scene: the demo tabletop at ``--density`` (1 = ~20k Gaussians, 15 = ~300k), language features from
its labels (one fixed unit vector per object plus noise, as ``tiger demo`` builds them before
training), target "ball" (cosine > 0.5 to its label vector).

Guidances:
  recolor        the built-in recolour ("make the ball red")
  analytic       the ideal denoiser of a ground-truth recoloured scene (SPEC §8): reports the PSNR
                 of the edited renders to the ground truth on the object's pixels (the error column)
  ip2p+mvdream   CSD with InstructPix2Pix + MVDream; ``--random-models full|tiny`` builds randomly
                 initialised models of the real architectures (same cost as the real weights) directly
                 on the device (benchmarks/guidance.py's build_models), in ``--dtype``

Per step: render (4 views; with ``--view-pool 0`` also the 4 original renders the guidance is
conditioned on, else those of the K pre-sampled camera sets, each when first drawn: stage view_pool), guidance,
backward through the rasterizer, optimizer (relevance-scaled Adam), densification (amortised).
Peak memory is torch.cuda.max_memory_allocated on CUDA.

Locality (tiger.eval.edit.locality, 6 views of 128²): PSNR outside the object's dilated footprint,
and its error split by where it comes from: ``fringe`` (pixels the object covered by less than 2 %
before the edit: its own faint edge, which any recolouring changes), ``spread`` (pixels only the
edited Gaussians reach after the edit), ``rest`` (no edited Gaussian reaches them: 100 dB unless
Gaussians outside the object changed; ``locality_rest_max_abs`` their largest difference). With
recolor/analytic, ``locality_exact_edit_dB`` is the ground-truth recolour's own locality.

    python -m benchmarks.edit                                      # CPU, demo scene, recolor + analytic
    python -m benchmarks.edit --device cuda --density 15 --guidance ip2p+mvdream --random-models full \\
        --steps 1200 --size 512 --warmup 20 --cuda-graph         # or: bash benchmarks/gpu/edit.sh
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import math
import time
from pathlib import Path
from typing import Optional

import torch

from benchmarks.common import gpu_timeline, print_table  # noqa: E402

from tiger.demo.run import label_features  # noqa: E402
from tiger.demo.scene import tabletop_scene  # noqa: E402
from tiger.edit import EditConfig, edit, resolve_target  # noqa: E402
from tiger.edit.guidance import RecolorGuidance  # noqa: E402
from tiger.edit.guidance.model_kernels import ModelKernels  # noqa: E402
from tiger.testing.ideal_denoiser import IdealDenoiserGuidance, render_targets  # noqa: E402
from tiger.edit.views import ObjectViews  # noqa: E402
from tiger.eval.edit import locality  # noqa: E402
from tiger.scene import render_rgb  # noqa: E402
from tiger.scene import GaussianScene  # noqa: E402
from tiger.scene.sh import rgb_to_sh  # noqa: E402
from tiger.utils.dtypes import DTYPE_NAMES  # noqa: E402

RED = (0.86, 0.08, 0.08)


def demo_scene(density: float, device: str) -> tuple[GaussianScene, torch.Tensor]:
    """(scene with lang [N, 64], the ball's label vector [64])."""
    lab = tabletop_scene(density)
    s = lab.scene.with_sh_degree(3)
    s.lang = label_features(lab)
    g = torch.Generator().manual_seed(0)  # label_features' table (same seed, same draw)
    table = torch.randn(len(lab.names), 64, generator=g)
    query = table[lab.names.index("ball")] / table[lab.names.index("ball")].norm()
    return s.to(device), query.to(device)


def diffusion_guidance(kind: str, size: str, device: str, dtype: torch.dtype, cuda_graph: bool, seed: int = 0,
                       fused_norms: Optional[bool] = None, concurrent: bool = True, kernels=None):
    """CSD with randomly initialised InstructPix2Pix / MVDream of the real architectures (``full``:
    SD-1.5 IP2P and SD-2.1 MVDream, built directly on the device by benchmarks/guidance.py);
    ``fused_norms`` as for the real loaders (None, their default: VAE and UNet fused on CUDA);
    ``concurrent``: MVDream on a side stream beside InstructPix2Pix (CSDGuidance's default);
    ``kernels``: both guidances' :class:`~tiger.edit.guidance.model_kernels.ModelKernels` (None:
    the default)."""
    from benchmarks.guidance import build_models, tokenizer

    from tiger.edit import CSDGuidance
    from tiger.edit.guidance import InstructPix2PixGuidance, MVDreamGuidance

    tok = tokenizer(Path("outputs/bench_edit_tokenizer"))
    ip2p_models, mv_models = build_models(size, device, dtype, tok, fused_norms)
    kw = {} if size == "full" else {"short_side": 64}
    ip = InstructPix2PixGuidance(ip2p_models, "make the ball look like a watermelon", cuda_graph=cuda_graph,
                                 generator=torch.Generator(device).manual_seed(seed), kernels=kernels,
                                 **kw) if "ip2p" in kind else None
    mv = MVDreamGuidance(mv_models, "a watermelon", cuda_graph=cuda_graph, image_size=256 if size == "full" else 32,
                         generator=torch.Generator(device).manual_seed(seed + 1),
                         kernels=kernels) if "mvdream" in kind else None
    return CSDGuidance(ip, mv, concurrent=concurrent)


def build(kind: str, scene: GaussianScene, mask: torch.Tensor, args):
    if kind == "recolor":
        return RecolorGuidance("make the ball red"), None
    if kind == "analytic":
        truth = scene.clone()
        truth.sh_dc[mask] = rgb_to_sh(torch.tensor(RED, device=scene.device)).expand(int(mask.sum()), 3)
        return IdealDenoiserGuidance(render_targets(truth, torch.ones(3, device=scene.device))), truth
    dtype = DTYPE_NAMES[args.dtype]
    fused = {"auto": None, "on": True, "off": False}[args.fused_norms]
    return diffusion_guidance(kind, args.random_models, args.device, dtype, args.cuda_graph, fused_norms=fused,
                              concurrent=not args.sequential_guidance,
                              kernels=ModelKernels.from_spec(args.model_kernels)), None


def profile_steps(scene: GaussianScene, tgt, guidance, cfg: EditConfig, args) -> dict:
    """``cfg.steps`` edit steps under torch.profiler: host (CPU) ms, GPU kernel ms and GPU span per stage, the GPU's busy
    share of the wall time and the host synchronisations, per step. The table goes to
    ``--profile-out``."""
    from torch.autograd import DeviceType
    from torch.profiler import ProfilerActivity, profile

    n = cfg.steps
    torch.cuda.synchronize()
    with profile(activities=[ProfilerActivity.CPU, ProfilerActivity.CUDA],
                 with_stack=bool(args.profile_trace)) as prof:
        t0 = time.perf_counter()
        edit(scene, tgt, guidance, config=cfg)
        torch.cuda.synchronize()
        wall = time.perf_counter() - t0
    busy, idle = gpu_timeline((e.time_range.start, e.time_range.end, e.name) for e in prof.events()
                              if e.device_type == DeviceType.CUDA)  # us
    gaps: dict[tuple[str, str], list[float]] = {}  # idle gaps by the kernels around them
    for a, b, before, after in idle:
        gaps.setdefault((before[:60], after[:60]), []).append(b - a)
    out = {"profile_steps": n, "profile_wall_ms/step": 1e3 * wall / n, "profile_gpu_busy_ms/step": 1e-3 * busy / n}
    worst = sorted(gaps.items(), key=lambda kv: -sum(kv[1]))[:12]
    out["gpu_idle_gaps"] = [{"after": k[0], "before": k[1], "count/step": len(v) / n,
                             "idle_ms/step": 1e-3 * sum(v) / n} for k, v in worst]
    averages = prof.key_averages()
    for ev in averages:
        dev_us = getattr(ev, "device_time_total", None)
        dev_us = ev.cuda_time_total if dev_us is None else dev_us
        if ev.key.startswith("edit::"):
            # two rows per stage: the host range (CPU time, its kernels' GPU time) and the GPU-side
            # annotation (no CPU time; GPU time = the stage's span on the GPU, idle gaps included)
            stage = ev.key[len("edit::"):]
            if ev.cpu_time_total > 0:
                out[f"host_{stage}_ms/step"] = 1e-3 * ev.cpu_time_total / n
                out[f"gpu_kernels_{stage}_ms/step"] = 1e-3 * dev_us / n
            else:
                out[f"gpu_span_{stage}_ms/step"] = 1e-3 * dev_us / n
        if "Synchronize" in ev.key or ev.key in ("cudaMemcpyAsync", "cudaMemcpy", "cudaStreamWaitEvent",
                                                "cudaGraphLaunch", "cudaLaunchKernel", "aten::item",
                                                "aten::_local_scalar_dense"):
            out[f"calls_{ev.key}/step"] = ev.count / n
    if args.profile_trace:
        prof.export_chrome_trace(args.profile_trace)  # chrome://tracing or ui.perfetto.dev
    if args.profile_out:
        text = "\n".join([json.dumps(out), averages.table(sort_by="cpu_time_total", row_limit=45),
                          averages.table(sort_by="cuda_time_total", row_limit=45)])
        from tiger.utils.io import atomic_write

        with atomic_write(args.profile_out, "w") as f:
            f.write(text)
    return out


def edit_config(args) -> EditConfig:
    """The benchmark's :class:`EditConfig` from its command-line arguments (:func:`parser`)."""
    return EditConfig(steps=args.steps, width=args.size, height=args.size, lrs={"sh_dc": args.lr_color},
                      densify_every=args.densify_every, densify_from=args.densify_every,
                      background=(1.0, 1.0, 1.0), progress=args.progress, checkpoint_every=0,
                      view_pool=args.view_pool, prefetch_views=not args.no_prefetch_views)


def run(args) -> dict:
    dev = args.device
    cuda = dev.startswith("cuda")
    scene, query = demo_scene(args.density, dev)
    tgt = resolve_target(scene, query, tau=0.5)
    t0 = time.perf_counter()
    guidance, truth = build(args.guidance, scene, tgt.mask, args)
    build_s = time.perf_counter() - t0
    cfg = edit_config(args)
    projected = None
    if args.warmup:  # CUDA graphs, cuDNN autotuning, allocator: not part of the edit's time
        edit(scene, tgt, guidance, config=dataclasses.replace(cfg, steps=args.warmup, progress=False))
        if cuda:
            torch.cuda.synchronize()
        t0 = time.perf_counter()
        warm = edit(scene, tgt, guidance, config=dataclasses.replace(cfg, steps=args.warmup, progress=False))
        if cuda:
            torch.cuda.synchronize()
        pool_s = warm.timings_s.get("view_pool", 0.0)  # once per pooled set (about one per warm-up step)
        per_step = (time.perf_counter() - t0 - pool_s) / args.warmup
        sets = min(args.view_pool, args.warmup)
        pool_s = pool_s / sets * min(args.view_pool, args.steps) if sets else 0.0  # the whole edit's
        projected = per_step * args.steps + pool_s
        if args.time_budget_s and projected > args.time_budget_s:  # keep within the device call
            cfg = dataclasses.replace(cfg, steps=max(args.warmup, int((args.time_budget_s - pool_s) / per_step)))
            print(f"projected {projected:.0f} s for {args.steps} steps > budget: timing {cfg.steps} steps", flush=True)
    if cuda:
        torch.cuda.synchronize()
        torch.cuda.reset_peak_memory_stats()
    t0 = time.perf_counter()
    res = edit(scene, tgt, guidance, config=cfg)
    if cuda:
        torch.cuda.synchronize()
    total = time.perf_counter() - t0
    n = cfg.steps
    row = {"device": dev, "gaussians": len(scene), "editable": tgt.count, "guidance": args.guidance,
           "view_pool": args.view_pool, "prefetch_views": cfg.prefetch_views, "steps": n, "size": args.size,
           "model_kernels": args.model_kernels or "default", "models_build_s": build_s, "edit_s": total,
           f"edit_{args.steps}_steps_s": total * args.steps / n}
    if projected is not None:
        row["warmup_projection_s"] = projected
    for k, v in res.timings_s.items():
        row[f"{k}_ms/step"] = 1e3 * v / n
    row["other_ms/step"] = 1e3 * (total - sum(res.timings_s.values())) / n
    if cuda:
        row["peak_GiB"] = torch.cuda.max_memory_allocated() / 2**30
    if cuda and args.profile_steps:
        prof = profile_steps(scene, tgt, guidance, dataclasses.replace(cfg, steps=args.profile_steps,
                                                                       progress=False), args)
        print("GPU idle gaps (the kernels around them):", json.dumps(prof.pop("gpu_idle_gaps")))
        row.update(prof)
    row["after"] = len(res.scene)
    white = torch.ones(3, device=scene.device)
    cams = ObjectViews(tgt.center, tgt.bbox_min, tgt.bbox_max, force_360=True, width=128, height=128).fixed(6, 15.0)
    loc = locality(scene, res.scene, cams, tgt.mask, res.editable, background=white)
    row["locality_dB"] = loc["psnr"]
    # where the locality error comes from (tiger.eval.edit.locality_parts): the object's faint edge,
    # pixels the edited Gaussians reach only after the edit, the rest (must stay at the cap)
    for part in ("fringe", "spread", "rest"):
        row[f"locality_{part}_dB"] = loc["parts"][part]["psnr"]
    row["locality_rest_max_abs"] = loc["parts"]["rest"]["max_abs_err"]
    if truth is not None or args.guidance == "recolor":
        ref = truth if truth is not None else build("analytic", scene, tgt.mask, args)[1]
        exact = ref.clone()  # the exact recolour, view-independent as the edit makes it: what a perfect edit scores
        exact.sh_rest[tgt.mask] = 0
        row["locality_exact_edit_dB"] = locality(scene, exact, cams, tgt.mask, tgt.mask, background=white)["psnr"]
        got, _ = render_rgb(res.scene, cams, white, footprint=res.editable)
        want, foot = render_rgb(ref, cams, white, footprint=tgt.mask)
        mse = float((got.clamp(0, 1) - want.clamp(0, 1)).square().mean(-1)[foot > 0.5].mean())
        row["object_PSNR_dB"] = -10 * math.log10(max(mse, 1e-12))
    return row


def parser() -> argparse.ArgumentParser:
    """The benchmark's command line (also read by benchmarks.gpu.edit_stage_kernels)."""
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--device", default="cpu")
    p.add_argument("--density", type=float, default=1.0, help="demo scene density (15 = ~300k Gaussians)")
    p.add_argument("--guidance", nargs="+", default=["recolor", "analytic"])
    p.add_argument("--random-models", default="full", help="full | tiny: random diffusion models of that size")
    p.add_argument("--dtype", default="bf16", choices=sorted(DTYPE_NAMES), help="diffusion models' dtype")
    p.add_argument("--cuda-graph", action="store_true", help="replay each guidance step as a CUDA graph")
    p.add_argument("--fused-norms", default="auto", choices=("auto", "on", "off"),
                   help="tiger's fused GroupNorm+SiLU in channels-last: auto = the loaders' default "
                        "(VAEs and UNets on CUDA, off on the CPU), on = both everywhere, off = torch's GroupNorm")
    p.add_argument("--model-kernels", default="", metavar="FIELD=on|off|auto,...",
                   help="the diffusion guidances' ModelKernels fields other than their defaults "
                        "(e.g. stacked_time_bias=off,cached_text_kv=off)")
    p.add_argument("--sequential-guidance", action="store_true",
                   help="run MVDream after InstructPix2Pix on one stream (default: beside it on a side stream)")
    p.add_argument("--warmup", type=int, default=0, help="untimed warm-up steps before the timed edit")
    p.add_argument("--time-budget-s", type=float, default=None,
                   help="time fewer steps when the warm-up projects more than this (the row says so)")
    p.add_argument("--steps", type=int, default=100)
    p.add_argument("--no-prefetch-views", action="store_true",
                   help="prepare a new pool set when its step comes, not beside the step before "
                        "(EditConfig.prefetch_views off; for A/B timing)")
    p.add_argument("--view-pool", type=int, default=EditConfig().view_pool,
                   help="camera sets pre-sampled, their original renders made when first drawn "
                        "(EditConfig.view_pool, default %(default)s as tiger edit; 0: fresh views every step)")
    p.add_argument("--size", type=int, default=128)
    p.add_argument("--lr-color", type=float, default=0.05)
    p.add_argument("--densify-every", type=int, default=EditConfig().densify_every,
                   help="densify every K steps, from step K (default %(default)s: EditConfig's, as tiger edit)")
    p.add_argument("--progress", action="store_true")
    p.add_argument("--profile-steps", type=int, default=0,
                   help="CUDA: after the timed edit, this many steps under torch.profiler (host vs GPU per stage)")
    p.add_argument("--profile-out", default=None, help="the profiler's tables go here")
    p.add_argument("--profile-trace", default=None, help="the profiled steps' host and GPU timeline (Chrome trace JSON)")
    p.add_argument("--json", default=None, help="also write the rows here")
    return p


def main() -> None:
    args = parser().parse_args()
    rows = []
    for kind in args.guidance:
        a = argparse.Namespace(**{**vars(args), "guidance": kind})
        rows.append(run(a))
        print(json.dumps(rows[-1]), flush=True)
        if args.json:
            Path(args.json).parent.mkdir(parents=True, exist_ok=True)
            Path(args.json).write_text(json.dumps(rows, indent=2))
    print_table(rows, "edit loop: time per stage (ms/step), total (s), quality (dB)")


if __name__ == "__main__":
    main()
