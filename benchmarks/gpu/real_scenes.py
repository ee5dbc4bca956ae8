"""The rasterizer on real scenes: ours against gsplat 1.5.3, per stage, C = 3 and 64.

Cases (``--cases``; each at the resolution named):
  snowmiku-1080p, snowmiku-4k  real SfM points of a public COLMAP reconstruction (the Snow Miku
      2023 plush, github.com/noname0310/snowmiku2023plush-splat, MIT licence; sparse/0/points3D.bin,
      cameras.bin, and output/cameras.json for the poses, whose images.bin is not stored there),
      initialised the 3DGS way (scale = root mean squared distance to the 3 nearest neighbours,
      identity rotations, opacity 0.1, colours of the points), seen from the capture's first
      camera at 1440x1080 and at its native 3958x2968. Data folder: ``--snowmiku`` (not in git).
  fox     the fox capture reconstructed by our trainer on this GPU (half resolution, a short
      schedule with densification), rendered at the full 1080x1920 from a held-out camera.
  heavy   benchmarks.common.heavy_tailed_scene (1e6 Gaussians) at 1920x1080.
  standard  benchmarks.common.standard_scene (1e6 Gaussians) at 1920x1080 (must not regress).

For each case: the distribution of screen radii (max of the two pixel radii of the visible
Gaussians) and of bounding-box tiles; then for C = 3 and 64: ours (load-balanced binning),
ours with the kernel choices of ``--before`` (default ``binning._serial=true``: the former
binning, whose tile lists must be identical; any field of rasterize_gaussians' ``binning`` and
``kernels`` settings, e.g. ``binning.path=global`` or ``kernels.backward_pixels_per_thread=1``),
and gsplat (packed, classic, same eps2d/near/far): median forward and forward+backward ms
(CUDA events), and per-stage GPU time from the profiler (project = projection + SH, bin,
sort, raster, backward, other) and the number of GPU operations (kernels, memsets, copies)
launched, averaged over a few forward+backward passes. Ours runs with ``check_finite=False``
(no input checks), as gsplat does none: like for like. For C = 3, ours' wall time is also split
on the host (until the forward returns, the backward call, the GPU tail after both), and the
case named by ``--host-profile`` gets a CPU-side profile (host_profile_<case>.txt in --out).
"""
from __future__ import annotations

import argparse
import functools
import json
import math
import os
import time
from pathlib import Path
from typing import Optional

import torch

REPO = Path(__file__).resolve().parents[2]
from benchmarks.common import cuda_time_ms, rel_err, table
from tests.render.standard_scenes import heavy_tailed_scene, standard_camera, standard_scene
from benchmarks.gpu.rasterize_vs_gsplat import gsplat_render, leaves, ours  # noqa: E402

import tiger  # noqa: E402
from tiger.ops.binning import BinningSettings  # noqa: E402
from tiger.ops.raster import RasterKernelSettings  # noqa: E402

PARAMS = ("means", "quats", "scales", "opacities", "colors")
STAGES = ("project", "bin", "sort", "raster", "backward", "other")


def log(*a: object) -> None:
    print(*a, flush=True)


# ------------------------------------------------------------------------------------------
# Scenes
# ------------------------------------------------------------------------------------------
def snowmiku(folder: Path, height: int, device: str) -> tuple[dict, torch.Tensor, torch.Tensor, int, int]:
    """3DGS-style initial scene from the COLMAP points, first camera scaled to ``height``."""
    from tiger.scene.colmap import read_cameras_binary, read_points3d_binary
    from tiger.scene.gaussian_scene import GaussianScene

    pts = read_points3d_binary(folder / "points3D.bin")
    cam = next(iter(read_cameras_binary(folder / "cameras.bin").values()))
    if cam.model != "PINHOLE":
        raise ValueError(f"{folder}/cameras.bin: expected a PINHOLE camera, got {cam.model}")
    fx, fy, cx, cy = cam.params
    views = json.loads((folder / "cameras.json").read_text())
    v = views[0]  # 3DGS cameras.json: 'position' = camera centre, 'rotation' = camera-to-world
    if (v["width"], v["height"]) != (cam.width, cam.height):
        raise ValueError(f"{folder}: cameras.json is {v['width']}x{v['height']}, cameras.bin "
                         f"{cam.width}x{cam.height}")
    R = torch.tensor(v["rotation"], dtype=torch.float64).T  # world-to-camera
    C = torch.tensor(v["position"], dtype=torch.float64)
    V = torch.eye(4, dtype=torch.float64)
    V[:3, :3] = R
    V[:3, 3] = -R @ C
    s = height / cam.height
    w, h = round(cam.width * s), height
    K = torch.tensor([[fx * s, 0, cx * s], [0, fy * s, cy * s], [0, 0, 1]], dtype=torch.float64)
    points = torch.from_numpy(pts.xyz).float().to(device)
    colors = torch.from_numpy(pts.rgb).float().div(255).to(device)
    gs = GaussianScene.from_points(points, colors, sh_degree=0, opacity=0.1)
    scene = {"means": gs.means, "quats": gs.quats, "scales": gs.scales, "opacities": gs.opacities,
             "colors": colors}
    return ({k: t.detach().float().contiguous().to(device) for k, t in scene.items()},
            V.float().to(device), K.float().to(device), w, h)


def fox(data: Path, device: str, iterations: int, budget_s: float, cache: Path,
        scene_file: Optional[Path] = None):
    """Our trainer on the fox (half resolution), then a held-out camera at full resolution.
    With ``scene_file``: the trained scene and camera are read from it when it exists, else
    written to it, so that two builds timed in one call render the same scene (the training
    stops at a time budget, so two trainings differ)."""
    if scene_file is not None and scene_file.is_file():
        saved = torch.load(scene_file, map_location=device)
        return (saved["scene"], saved["viewmat"], saved["K"], saved["width"], saved["height"],
                {**saved["info"], "scene_file": str(scene_file)})
    from tiger.recon import ReconConfig, Trainer, load_views
    from tiger.scene.dataset import load_dataset

    ds = load_dataset(data)
    train_c, test_c = ds.split(8)
    tc, ti = load_views(train_c, 2.0, cache_dir=cache)
    cfg = ReconConfig.scaled(iterations, sh_degree=3, init_random_points=100_000,
                             time_budget_s=budget_s, eval_every=0, progress=False)
    t0 = time.perf_counter()
    tr = Trainer(tc, ti, cfg, device=device)
    gs = tr.fit()
    fit_s = time.perf_counter() - t0
    full_c, _ = load_views(test_c[:1], 1.0, cache_dir=cache)
    cam = full_c[0].to(device, torch.float32)
    gs = gs.to(device, torch.float32)
    with torch.no_grad():
        rgb = gs.view_colors(cam, gs.sh_degree)
    scene = {"means": gs.means, "quats": gs.quats, "scales": gs.scales, "opacities": gs.opacities,
             "colors": rgb}
    info = {"fit_steps": tr.step, "fit_s": fit_s, "gaussians": len(gs)}
    scene = {k: t.detach().float().contiguous() for k, t in scene.items()}
    if scene_file is not None:
        from tiger.utils.io import atomic_write

        with atomic_write(scene_file, "wb") as f:
            torch.save({"scene": scene, "viewmat": cam.viewmat.float(), "K": cam.K.float(),
                        "width": cam.width, "height": cam.height, "info": info}, f)
    return scene, cam.viewmat.float(), cam.K.float(), cam.width, cam.height, info


def with_channels(scene: dict, C: int) -> dict:
    """The scene with C channels: its RGB for C = 3, seeded standard-normal features otherwise."""
    s = dict(scene)
    if C != scene["colors"].shape[1]:
        g = torch.Generator(device="cpu").manual_seed(C)
        s["colors"] = torch.randn(scene["means"].shape[0], C, generator=g).to(scene["means"])
    return s


# ------------------------------------------------------------------------------------------
# Measurements
# ------------------------------------------------------------------------------------------
def project(scene, V, K, w, h):
    return torch.ops.tiger.project_gaussians(scene["means"], scene["quats"], scene["scales"],
                                             scene["opacities"], V, K, w, h, 0.3, 0.01, 1e10,
                                             1 / 255, False)


def radii_stats(scene, V, K, w, h) -> dict:
    """Screen radii of the visible Gaussians (px) and their bounding-box tiles (16 px)."""
    m2, cn, d, op, r = project(scene, V, K, w, h)
    vis = (r[:, 0] > 0) & (r[:, 1] > 0)
    rmax = r[vis].max(1).values.double()
    u, v = m2[vis, 0].double(), m2[vis, 1].double()
    rx, ry = r[vis, 0].double(), r[vis, 1].double()
    tx, ty = math.ceil(w / 16), math.ceil(h / 16)
    bx = ((u + rx) / 16).floor().add(1).clamp(0, tx) - ((u - rx) / 16).floor().clamp(0, tx)
    by = ((v + ry) / 16).floor().add(1).clamp(0, ty) - ((v - ry) / 16).floor().clamp(0, ty)
    tiles = (bx * by).clamp_min(0)
    to, ids = torch.ops.tiger.bin_gaussians(m2, cn, op, d, r, w, h, 16, 1 / 255)
    q = torch.tensor([0.5, 0.9, 0.99, 0.999], dtype=torch.float64, device=rmax.device)
    pr = torch.quantile(rmax, q).tolist() if rmax.numel() else [0.0] * 4
    big = tiles > 1000
    return {"N": int(r.shape[0]), "visible": int(vis.sum()), "r_mean": float(rmax.mean()),
            "r_p50": pr[0], "r_p90": pr[1], "r_p99": pr[2], "r_p99.9": pr[3],
            "r_max": float(rmax.max()) if rmax.numel() else 0.0,
            "bbox_tiles": int(tiles.sum()), "bbox_tiles_max": int(tiles.max()) if tiles.numel() else 0,
            "gauss_over_1000_tiles": int(big.sum()), "share_of_bbox_tiles_in_them": float(tiles[big].sum() / tiles.sum().clamp_min(1)),
            "isects": int(ids.numel()), "tile_list_max": int((to[1:] - to[:-1]).max())}


def stage_kind(name: str) -> str:
    n = name.lower()
    if "bwd" in n or "backward" in n:
        return "backward"
    if "radix" in n or "onesweep" in n or ("sort_" in n and "tiles_kernel" in n):
        return "sort"
    if "project" in n or "sh_kernel" in n or "harmonics" in n:
        return "project"
    if "bin_cuda" in n or any(k in n for k in ("candidates_kernel", "count_balanced", "emit_balanced", "count_serial",
                            "emit_serial", "count_small", "emit_small", "count_large", "emit_large",
                            "ranges_kernel", "scan", "isect", "intersect", "depth_keys",
                            "scatter_rank", "order_counts")):
        return "bin"
    if "raster" in n or "forward_kernel" in n:
        return "raster"
    return "other"


def profiled_passes(render, scene, V, K, w, h, reps: int, activities: list):
    """The profiler of ``reps`` forward+backward passes (after two warm-up passes)."""
    from torch.profiler import profile

    C = scene["colors"].shape[1]
    vc = torch.randn(h, w, C, device="cuda", generator=torch.Generator(device="cuda").manual_seed(7))
    s = leaves(scene, PARAMS)
    for _ in range(2):
        render(s, V, K, w, h)[0].backward(vc)
    torch.cuda.synchronize()
    with profile(activities=activities) as prof:
        for _ in range(reps):
            for t in s.values():
                t.grad = None
            render(s, V, K, w, h)[0].backward(vc)
        torch.cuda.synchronize()
    return prof


def stage_times(render, scene, V, K, w, h, reps: int = 5) -> tuple[dict, dict]:
    """Per-stage GPU ms of one forward+backward (profiler, mean of ``reps``) and the raw
    per-kernel ms."""
    from torch.autograd import DeviceType
    from torch.profiler import ProfilerActivity

    prof = profiled_passes(render, scene, V, K, w, h, reps, [ProfilerActivity.CUDA])
    per_kernel: dict = {}
    launches = 0
    for e in prof.events():
        if e.device_type != DeviceType.CUDA:
            continue
        launches += 1
        per_kernel[e.name] = per_kernel.get(e.name, 0.0) + e.time_range.elapsed_us() / 1e3 / reps
    stages = {k: 0.0 for k in STAGES}
    for name, ms in per_kernel.items():
        stages[stage_kind(name)] += ms
    stages["total"] = sum(stages[k] for k in STAGES)
    stages["launches"] = launches / reps  # kernels, memsets and copies per forward+backward
    return stages, per_kernel


def kernel_choices(spec: str) -> dict:
    """``"binning.path=global,kernels.backward_pixels_per_thread=1"`` -> the ``binning`` and
    ``kernels`` keywords of rasterize_gaussians (fields not named keep their defaults)."""
    defaults = {"binning": BinningSettings(), "kernels": RasterKernelSettings()}
    fields: dict = {"binning": {}, "kernels": {}}
    for item in filter(None, spec.split(",")):
        key, _, value = item.partition("=")
        group, _, name = key.strip().partition(".")
        if group not in defaults or not hasattr(defaults[group], name) or not value:
            raise SystemExit(f"--before: {item!r} is not FIELD=VALUE with FIELD one of "
                             f"binning.<{'|'.join(vars(defaults['binning']))}>, "
                             f"kernels.<{'|'.join(vars(defaults['kernels']))}>")
        kind = type(getattr(defaults[group], name))
        fields[group][name] = value.lower() in ("1", "true") if kind is bool else kind(value)
    return {"binning": BinningSettings(**fields["binning"]),
            "kernels": RasterKernelSettings(**fields["kernels"])}


def bin_op(m2, cn, op, d, r, w, h, settings: BinningSettings = BinningSettings()):
    return torch.ops.tiger.bin_gaussians(m2, cn, op, d, r, w, h, 16, 1 / 255, *settings.op_args())


def same_lists(scene, V, K, w, h) -> bool:
    """Balanced and former binning give identical tile lists (same pairs, same order)."""
    m2, cn, d, op, r = project(scene, V, K, w, h)
    a = bin_op(m2, cn, op, d, r, w, h)
    b = bin_op(m2, cn, op, d, r, w, h, BinningSettings(_serial=True))
    return bool(torch.equal(a[0], b[0]) and torch.equal(a[1], b[1]))


def bin_op_times(scene, V, K, w, h, iters, sort_keys_sweep=()) -> dict:
    """ms of the binning op alone (walks, sorts and its host synchronisation): the default, each
    of the two paths forced (path="tiles" | "global": per-tile sort, global sort), the
    one-thread-per-Gaussian walk (_serial) and the default with each per-tile sort size of
    ``sort_keys_sweep`` (block_sort_keys: longer tile lists are merged from runs)."""
    m2, cn, d, op, r = project(scene, V, K, w, h)
    variants = [("bin_op", BinningSettings()), ("bin_op_tiles", BinningSettings(path="tiles")),
                ("bin_op_global", BinningSettings(path="global")),
                ("bin_op_former", BinningSettings(_serial=True))]
    variants += [(f"bin_op_sortkeys{k}", BinningSettings(block_sort_keys=k)) for k in sort_keys_sweep]
    return {name: cuda_time_ms(lambda: bin_op(m2, cn, op, d, r, w, h, settings), iters=iters)
            for name, settings in variants}


def time_pair(render, scene, V, K, w, h, iters):
    C = scene["colors"].shape[1]
    vc = torch.randn(h, w, C, device="cuda", generator=torch.Generator(device="cuda").manual_seed(1))
    fwd_scene = {k: v.detach() for k, v in scene.items()}
    fwd = cuda_time_ms(lambda: render(fwd_scene, V, K, w, h), iters=iters)
    s = leaves(scene, PARAMS)

    def fb():
        for t in s.values():
            t.grad = None
        render(s, V, K, w, h)[0].backward(vc)
    return fwd, cuda_time_ms(fb, iters=iters)


def host_split(render, scene, V, K, w, h, iters) -> dict:
    """Where the wall time of one forward+backward goes on the host (median ms): until the
    forward returns (it includes waiting for the binning's synchronisation), the backward call,
    and the rest of the GPU work after both returned (the final synchronisation)."""
    C = scene["colors"].shape[1]
    vc = torch.randn(h, w, C, device="cuda", generator=torch.Generator(device="cuda").manual_seed(1))
    s = leaves(scene, PARAMS)
    rows = []
    for i in range(iters + 3):
        for t in s.values():
            t.grad = None
        torch.cuda.synchronize()
        t0 = time.perf_counter()
        out = render(s, V, K, w, h)[0]
        t1 = time.perf_counter()
        out.backward(vc)
        t2 = time.perf_counter()
        torch.cuda.synchronize()
        t3 = time.perf_counter()
        if i >= 3:
            rows.append((t1 - t0, t2 - t1, t3 - t2, t3 - t0))
    med = [sorted(r[k] for r in rows)[len(rows) // 2] * 1e3 for k in range(4)]
    return {"host_fwd": med[0], "host_bwd_call": med[1], "gpu_tail": med[2], "wall": med[3]}


def host_profile(render, scene, V, K, w, h, path: Path, reps: int = 5) -> None:
    """The CPU side of a few forward+backward passes (profiler, CPU and CUDA activity): the
    ops with the most self CPU time, written to ``path``."""
    from torch.profiler import ProfilerActivity

    prof = profiled_passes(render, scene, V, K, w, h, reps,
                           [ProfilerActivity.CPU, ProfilerActivity.CUDA])
    table = prof.key_averages().table(sort_by="self_cpu_time_total", row_limit=30)
    path.write_text(f"{reps} forward+backward passes\n{table}\n")


def bench_case(name, scene, V, K, w, h, args, have_gsplat) -> dict:
    res = {"case": name, "width": w, "height": h, "radii": radii_stats(scene, V, K, w, h)}
    res["bin_op"] = bin_op_times(scene, V, K, w, h, args.iters, args.sort_keys_sweep)
    log(f"== {name} {w}x{h}: radii {fmt(res['radii'])}; {fmt(res['bin_op'])}")
    res["rows"], res["stages"], res["kernels"] = [], [], {}
    for C in args.channels:
        sc = with_channels(scene, C)
        row = {"case": name, "C": C}
        row["ours_fwd"], row["ours_fwdbwd"] = time_pair(ours, sc, V, K, w, h, args.iters)
        if C == 3:
            row.update({f"ours_{k}": v for k, v in host_split(ours, sc, V, K, w, h, args.iters).items()})
            if args.host_profile == name:
                host_profile(ours, sc, V, K, w, h, args.out / f"host_profile_{name}.txt")
        before = functools.partial(ours, **args.before)
        row["before_fwd"], row["before_fwdbwd"] = time_pair(before, sc, V, K, w, h, args.iters)
        st_before, _ = stage_times(before, sc, V, K, w, h)
        row["identical_lists"] = same_lists(sc, V, K, w, h)
        st, kern = stage_times(ours, sc, V, K, w, h)
        res["stages"].append({"case": name, "C": C, "who": "ours", **st})
        res["stages"].append({"case": name, "C": C, "who": f"ours ({args.before_label})", **st_before})
        res["kernels"][f"ours C={C}"] = kern
        row["bin_share_of_fwd"] = (st["bin"] + st["sort"]) / row["ours_fwd"]
        if have_gsplat:
            row["gs_fwd"], row["gs_fwdbwd"] = time_pair(gsplat_render, sc, V, K, w, h, args.iters)
            row["fwd_ratio"] = row["ours_fwd"] / row["gs_fwd"]
            row["fwdbwd_ratio"] = row["ours_fwdbwd"] / row["gs_fwdbwd"]
            gst, gkern = stage_times(gsplat_render, sc, V, K, w, h)
            res["stages"].append({"case": name, "C": C, "who": "gsplat", **gst})
            res["kernels"][f"gsplat C={C}"] = gkern
            with torch.no_grad():
                a = ours({k: v.detach() for k, v in sc.items()}, V, K, w, h)[0]
                b = gsplat_render({k: v.detach() for k, v in sc.items()}, V, K, w, h)[0]
            row["img_rel_diff_vs_gsplat"] = rel_err(a, b)
        res["rows"].append(row)
        log(fmt(row))
        del sc
        torch.cuda.empty_cache()
    return res


def fmt(r: dict) -> dict:
    return {k: (f"{v:.3g}" if isinstance(v, float) else v) for k, v in r.items()}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--cases", default="snowmiku-1080p,snowmiku-4k,fox,heavy,standard")
    p.add_argument("--channels", type=lambda s: [int(x) for x in s.split(",")], default=[3, 64])
    p.add_argument("--iters", type=int, default=20)
    p.add_argument("--snowmiku", type=Path, default=REPO / ".carry" / "realscene" / "snowmiku")
    p.add_argument("--fox-data", type=Path, default=REPO.parent / "shared" / "data" / "fox")
    p.add_argument("--fox-iterations", type=int, default=3000)
    p.add_argument("--fox-budget", type=float, default=40.0, help="seconds of training")
    p.add_argument("--fox-scene", type=Path, default=None,
                   help="file of the trained fox scene: read if it exists, else written (the same "
                        "scene for two builds timed in one call)")
    p.add_argument("--n", type=int, default=1_000_000, help="Gaussians of the synthetic cases")
    p.add_argument("--no-gsplat", action="store_true")
    p.add_argument("--sort-keys-sweep", type=lambda s: [int(x) for x in s.split(",") if x], default=[],
                   help="also time the binning op with these shared-memory tile-sort sizes "
                        "(block_sort_keys, powers of two <= 4096)")
    p.add_argument("--host-profile", default="snowmiku-1080p",
                   help="case whose C=3 forward+backward is profiled on the CPU side (file in --out)")
    p.add_argument("--before", default="binning._serial=true", metavar="FIELD=VALUE[,FIELD=VALUE]",
                   help="kernel choices of the 'before' columns: fields of rasterize_gaussians' "
                        "binning / kernels settings, e.g. binning.path=global or "
                        "kernels.backward_pixels_per_thread=1 (default: the former binning)")
    p.add_argument("--out", type=Path, default=Path(os.environ.get("OUT", "outputs/real_scenes")))
    args = p.parse_args()
    args.before_label = args.before
    args.before = kernel_choices(args.before)
    args.out.mkdir(parents=True, exist_ok=True)
    torch.backends.cuda.matmul.allow_tf32 = False
    have_gsplat = False
    if not args.no_gsplat:
        try:
            from gsplat.cuda._backend import _C
            have_gsplat = _C is not None
        except Exception as exc:  # pragma: no cover - depends on the machine
            log(f"gsplat unavailable: {exc!r}")
    log(f"device: {torch.cuda.get_device_name()}, torch {torch.__version__}, gsplat: {have_gsplat}")
    results = []
    for case in filter(None, args.cases.split(",")):
        try:
            if case.startswith("snowmiku"):
                hgt = 1080 if case.endswith("1080p") else 2968
                sc, V, K, w, h = snowmiku(args.snowmiku, hgt, "cuda")
                info = {}
            elif case == "fox":
                sc, V, K, w, h, info = fox(args.fox_data, "cuda", args.fox_iterations, args.fox_budget,
                                          Path("/tmp/tiger_fox_cache"), args.fox_scene)
            elif case in ("heavy", "standard"):
                make = heavy_tailed_scene if case == "heavy" else standard_scene
                sc = make(args.n, 3, device="cuda")
                w, h = 1920, 1080
                V, K = standard_camera(w, h, device="cuda")
                info = {}
            else:
                raise ValueError(f"unknown case {case}")
        except Exception as exc:  # a missing data folder must not stop the other cases
            log(f"== {case}: SKIPPED ({exc!r})")
            results.append({"case": case, "skipped": repr(exc)})
            continue
        r = bench_case(case, sc, V, K, w, h, args, have_gsplat)
        r["info"] = info
        results.append(r)
        (args.out / "real_scenes.json").write_text(json.dumps(results, indent=1, default=float))
        del sc
        torch.cuda.empty_cache()
    log("")
    done = [r for r in results if "rows" in r]
    log("== Screen radii (px, max of the two radii, visible Gaussians) and 16-px bounding-box tiles")
    radii = [{"case": r["case"], "size": f"{r['width']}x{r['height']}", **r["radii"], **r["bin_op"]}
             for r in done]
    log(table([fmt(x) for x in radii], list(radii[0].keys())) if radii else "(none)")
    log(f"\n== Speed (median ms of CUDA events); before = ours with {args.before_label}")
    rows = [x for r in done for x in r["rows"]]
    if rows:
        log(table([fmt(x) for x in rows], list(dict.fromkeys(k for x in rows for k in x))))
    log("\n== Per-stage GPU ms of one forward+backward (profiler)")
    st = [x for r in done for x in r["stages"]]
    if st:
        log(table([fmt(x) for x in st], list(st[0].keys())))


if __name__ == "__main__":
    main()
