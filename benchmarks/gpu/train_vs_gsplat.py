"""Time per training iteration of our trainer with our rasteriser and with gsplat 1.5.3's
swapped in, same process, same loop.

The fox capture at full resolution (1080x1920, 43 training views), 1,000,000 Gaussians
initialised at random in the views (tiger.recon's default initialisation), SH degree 3 active
from the start, densification off so that every variant trains the same number of Gaussians.
Every variant is warmed up first; then each timed run starts from one saved checkpoint (scene,
Adam state, view order), so all of them train the same steps on the same scene.
Each step is tiger.recon.Trainer.train_step (render, L1 + D-SSIM loss, backward, Adam); only
``scene.render`` is swapped. Two wall times: one step synchronised before and after (median),
and steps run back to back without reading the metrics back, as ``Trainer.fit`` runs them. Variants run in the order ours, gsplat (packed=False, its
trainer's default), gsplat (packed=True), ours again; median wall ms per step after warm-up,
and the GPU time of a step (sum of kernel times, profiler) with its costliest kernels, which
tells the rasteriser's share of the step from the rest (loss, Adam, Python). ``--ablation``
adds runs of ours with other kernel choices (e.g. kernels.backward_pixels_per_thread=1: one
pixel per backward thread), left out of the speed-ups.
"""
from __future__ import annotations

import argparse
import functools
import json
import statistics
import time
from pathlib import Path

import torch

REPO = Path(__file__).resolve().parents[2]


def gsplat_renderer(scene, packed: bool):
    """A drop-in for GaussianScene.render (the keys the trainer reads) backed by gsplat."""
    from gsplat import rasterization

    from tiger.scene.sh import num_sh_bases

    def render(camera, *, sh_degree=None, background=None, **_):
        deg = scene.sh_degree if sh_degree is None else int(sh_degree)
        cam = camera.to(device=scene.device, dtype=scene.dtype)
        col, alpha, meta = rasterization(
            scene.means, scene.quats, scene.scales, scene.opacities, scene.sh[:, :num_sh_bases(deg)],
            cam.viewmat[None], cam.K[None], cam.width, cam.height, sh_degree=deg, near_plane=0.01,
            far_plane=1e10, eps2d=0.3, packed=packed, tile_size=16, rasterize_mode="classic")
        color, alpha = col[0], alpha[0, ..., 0]
        if background is not None:  # composited here: gsplat 1.5.3 rejected a [1, 3] background
            color = color + (1 - alpha)[..., None] * background  # with packed=True on the H100
        return {"color": color, "alpha": alpha, "means2d": meta["means2d"], "radii": meta["radii"]}
    return render


def time_steps(tr, steps: int, warmup: int) -> tuple[float, float, float]:
    """Median ms of one step synchronised on both sides, ms per step of ``steps`` steps run back
    to back as ``Trainer.fit`` runs them (no read-back of the metrics), and the last PSNR."""
    times = []
    for i in range(warmup + steps):
        torch.cuda.synchronize()
        t0 = time.perf_counter()
        info = tr.train_step()
        torch.cuda.synchronize()
        if i >= warmup:
            times.append((time.perf_counter() - t0) * 1e3)
    torch.cuda.synchronize()
    t0 = time.perf_counter()
    for _ in range(steps):
        tr.train_step(read_back=False)
    torch.cuda.synchronize()
    pipelined = (time.perf_counter() - t0) * 1e3 / steps
    return statistics.median(times), pipelined, info["psnr"]


def step_profile(tr, steps: int = 3) -> tuple[float, list]:
    """GPU ms per step (sum of kernel times) and every kernel's ms per step, costliest first."""
    from torch.autograd import DeviceType
    from torch.profiler import ProfilerActivity, profile

    torch.cuda.synchronize()
    with profile(activities=[ProfilerActivity.CUDA]) as prof:
        for _ in range(steps):
            tr.train_step()
        torch.cuda.synchronize()
    per: dict = {}
    for e in prof.events():
        if e.device_type == DeviceType.CUDA:
            per[e.name] = per.get(e.name, 0.0) + e.time_range.elapsed_us() / 1e3 / steps
    ranked = sorted(per.items(), key=lambda kv: -kv[1])
    return sum(per.values()), [(round(ms, 4), name[:100]) for name, ms in ranked]


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--data", type=Path, default=REPO.parent / "shared" / "data" / "fox")
    p.add_argument("--gaussians", type=int, default=1_000_000)
    p.add_argument("--steps", type=int, default=60)
    p.add_argument("--warmup", type=int, default=10)
    p.add_argument("--json", type=Path, default=None)
    p.add_argument("--ablation", action="append", default=[], metavar="FIELD=VALUE[,FIELD=VALUE]",
                   help="also time ours with these kernel choices: fields of the renderer's "
                        "binning / kernels settings, e.g. kernels.backward_pixels_per_thread=1 "
                        "(a variant named 'ablation: ...', left out of the speed-ups); repeatable")
    args = p.parse_args()
    from tiger.recon import ReconConfig, Trainer, load_views
    from tiger.scene.dataset import load_dataset

    ds = load_dataset(args.data)
    train_c, _ = ds.split(8)
    out = Path("/tmp/tiger_fox_cache_full")
    t0 = time.perf_counter()
    cams, imgs = load_views(train_c, 1.0, cache_dir=out)
    print(f"fox: {len(cams)} views at {cams[0].width}x{cams[0].height}, loaded in "
          f"{time.perf_counter() - t0:.1f} s", flush=True)
    cfg = ReconConfig(iterations=10**6, densify=False, init_random_points=args.gaussians,
                      sh_degree=3, sh_increase_every=0, eval_every=0, progress=False)
    tr = Trainer(cams, imgs, cfg, device="cuda")
    tr.active_sh = 3
    n = len(tr.scene)
    print(f"{n} Gaussians, SH degree {tr.active_sh}", flush=True)
    rows = []
    variants = [("ours", None), ("gsplat packed=False", False), ("gsplat packed=True", True),
                ("ours (again)", None)]
    from benchmarks.gpu.real_scenes import kernel_choices

    ablations = {f"ablation: {a}": kernel_choices(a) for a in args.ablation}
    variants += [(name, None) for name in ablations]

    def use(packed, name=""):
        tr.active_sh = 3
        tr.scene.__dict__.pop("render", None)   # the scene's own method
        if packed is not None:
            tr.scene.render = gsplat_renderer(tr.scene, packed)
        elif name in ablations:  # the scene's method with other kernel choices
            tr.scene.render = functools.partial(type(tr.scene).render, tr.scene, **ablations[name])

    # Every variant once (gsplat's JIT build, allocator and clocks warm), then each timed run
    # starts from the same checkpoint: the same scene, Adam state and view order, so every
    # variant trains exactly the same steps (the scene changes as it trains: later runs would
    # otherwise render a different scene).
    for _, packed in variants[:3]:
        use(packed)
        for _ in range(args.warmup):
            tr.train_step(read_back=False)
    torch.cuda.synchronize()
    start = Path(f"/tmp/train_vs_gsplat_{n}.pt")
    tr.save(start)
    for name, packed in variants:
        tr.load(start)
        use(packed, name)
        torch.cuda.reset_peak_memory_stats()
        ms, piped, ps = time_steps(tr, args.steps, args.warmup)
        gpu_ms, top = step_profile(tr)
        rows.append({"variant": name, "ms_per_step": ms, "pipelined_ms_per_step": piped, "steps_per_s": 1e3 / ms,
                     "peak_GiB": torch.cuda.max_memory_allocated() / 2**30, "psnr_last": ps,
                     "gpu_ms_per_step": gpu_ms, "top_kernels": top})
        print({k: v for k, v in rows[-1].items() if k != "top_kernels"}, flush=True)
        for t in top[:16]:
            print("   ", t, flush=True)
    use(None)
    best_gs = min(r["ms_per_step"] for r in rows if r["variant"].startswith("gsplat"))
    ours_ms = statistics.median([r["ms_per_step"] for r in rows if r["variant"].startswith("ours")])
    # (ablations are named "ablation: ..." and count in neither)
    best_gs_p = min(r["pipelined_ms_per_step"] for r in rows if r["variant"].startswith("gsplat"))
    ours_p = statistics.median([r["pipelined_ms_per_step"] for r in rows if r["variant"].startswith("ours")])
    print(f"\n== Training iteration at {cams[0].width}x{cams[0].height}, {n} Gaussians "
          f"(median of {args.steps} steps after {args.warmup})")
    print("| variant | ms / step (synchronised) | ms / step (back to back) | GPU ms / step (kernels) | "
          "peak GiB |\n|---|---:|---:|---:|---:|")
    for r in rows:
        print(f"| {r['variant']} | {r['ms_per_step']:.2f} | {r['pipelined_ms_per_step']:.2f} | "
              f"{r['gpu_ms_per_step']:.2f} | {r['peak_GiB']:.2f} |")
    print(f"speed-up of ours over the faster gsplat variant: {best_gs / ours_ms:.2f}x per synchronised step, "
          f"{best_gs_p / ours_p:.2f}x back to back")
    if args.json:
        args.json.write_text(json.dumps({"gaussians": n, "width": cams[0].width,
                                         "height": cams[0].height, "rows": rows,
                                         "speedup": best_gs / ours_ms,
                                         "speedup_back_to_back": best_gs_p / ours_p}, indent=1))


if __name__ == "__main__":
    main()
