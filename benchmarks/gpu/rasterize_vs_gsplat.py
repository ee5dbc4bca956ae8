"""TIGER's CUDA rendering core against gsplat 1.5.3, same run, same scene (tests/render/standard_scenes.py).

Tables printed (and written as JSON with --json):
  1. speed: forward, forward+backward, features-only backward (ours) vs gsplat's backward
     with only the colours requiring grad (like for like) and with every input requiring grad;
     median of CUDA-event times after warm-up; peak GPU memory of one forward+backward.
  2. error: ours and gsplat against the float64 dense reference on a smaller case.
  3. sweep: time against error of the rendering core (float64, float32, float16/bfloat16
     channel storage).
  4. stages: time of each op of our pipeline; each kernel's channel block (64 or 32).
  5. floor: bytes the forward pass must move / measured copy bandwidth.

Run on a CUDA machine after building tiger with CUDA; gsplat is optional (--no-gsplat).
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

import torch

from benchmarks.common import cuda_copy_bandwidth, cuda_time_ms, rel_err, table
from tests.render.standard_scenes import standard_camera, standard_scene

import tiger  # noqa: E402
from tiger.render.reference import render_ref  # noqa: E402

GiB = float(1 << 30)
PARAMS = ("means", "quats", "scales", "opacities", "colors")


def log(*a: object) -> None:
    print(*a, flush=True)


# ------------------------------------------------------------------------------------------
# Renderers with one signature: f(scene, viewmat, K, w, h) -> (color [H,W,C], alpha [H,W])
# ------------------------------------------------------------------------------------------
def ours(s, V, K, w, h, **kernel_choices):
    """``kernel_choices``: rasterize_gaussians' ``binning`` / ``kernels`` settings (default: the
    defaults)."""
    out = tiger.rasterize_gaussians(s["means"], s["quats"], s["scales"], s["opacities"],
                                    s["colors"], V, K, w, h, check_finite=False, **kernel_choices)
    return out["color"], out["alpha"]


def gsplat_render(s, V, K, w, h):
    from gsplat import rasterization
    col, alpha, _ = rasterization(s["means"], s["quats"], s["scales"], s["opacities"],
                                  s["colors"], V[None], K[None],
                                  w, h, near_plane=0.01, far_plane=1e10, eps2d=0.3, packed=True,
                                  tile_size=16, rasterize_mode="classic")
    return col[0], alpha[0, ..., 0]


def leaves(scene, which):
    return {k: (v.detach().clone().requires_grad_(k in which)) for k, v in scene.items()}


def measure(render, scene, V, K, w, h, iters, features_only=False):
    """fwd ms, fwd+bwd ms, bwd-only ms, peak GiB of one fwd+bwd."""
    C = scene["colors"].shape[1]
    g = torch.Generator(device="cuda").manual_seed(1)
    v_color = torch.randn(h, w, C, device="cuda", generator=g)
    fwd_scene = {k: v.detach() for k, v in scene.items()}
    fwd = cuda_time_ms(lambda: render(fwd_scene, V, K, w, h), iters=iters)
    grad_set = ("colors",) if features_only else PARAMS
    s = leaves(scene, grad_set)

    def fwd_bwd():
        for t in s.values():  # a fresh .grad each time: no accumulation kernels timed
            t.grad = None
        col, _ = render(s, V, K, w, h)
        col.backward(v_color)

    fb = None
    if not features_only:
        fb = cuda_time_ms(fwd_bwd, iters=iters)

    def setup():
        for t in s.values():
            t.grad = None
        col, _ = render(s, V, K, w, h)
        return col

    bwd = cuda_time_ms(lambda col: col.backward(v_color), iters=iters, setup=setup)
    torch.cuda.synchronize()
    torch.cuda.empty_cache()
    torch.cuda.reset_peak_memory_stats()
    if features_only:
        setup().backward(v_color)
    else:
        fwd_bwd()
    torch.cuda.synchronize()
    peak = torch.cuda.max_memory_allocated() / GiB
    for t in s.values():
        t.grad = None
    return fwd, fb, bwd, peak


def speed_table(args, have_gsplat):
    rows = []
    w, h = args.width, args.height
    V, K = standard_camera(w, h, device="cuda")
    for n in args.sizes:
        for C in args.channels:
            scene = standard_scene(n, C, device="cuda")
            with torch.no_grad():
                n_isects = tiger.rasterize_gaussians(*[scene[k] for k in PARAMS], V, K, w, h,
                                                     check_finite=False)["n_isects"]
            r = {"N": n, "C": C, "isects": n_isects}
            f, fb, _, peak = measure(ours, scene, V, K, w, h, args.iters)
            _, _, fo_bwd, fo_peak = measure(ours, scene, V, K, w, h, args.iters, features_only=True)
            r.update(ours_fwd=f, ours_fwdbwd=fb, ours_feat_bwd=fo_bwd, ours_peak=peak,
                     ours_feat_peak=fo_peak)
            if have_gsplat:
                gf, gfb, gbwd, gpeak = measure(gsplat_render, scene, V, K, w, h, args.iters)
                # Like for like: gsplat's backward with only the colours requiring grad too.
                _, _, gfo_bwd, _ = measure(gsplat_render, scene, V, K, w, h, args.iters,
                                           features_only=True)
                r.update(gs_fwd=gf, gs_fwdbwd=gfb, gs_bwd=gbwd, gs_peak=gpeak,
                         gs_feat_bwd=gfo_bwd, x_fwdbwd=gfb / fb,
                         x_feat_vs_gs_feat_bwd=gfo_bwd / fo_bwd, x_feat_vs_gs_bwd=gbwd / fo_bwd)
            rows.append(r)
            log(fmt_rows([r])[0])
            del scene
            torch.cuda.empty_cache()
    return rows


def fmt_num(v: float) -> str:
    if v != v or v == 0.0:
        return f"{v:.3f}" if v == v else "nan"
    return f"{v:.2e}" if abs(v) < 0.01 else f"{v:.3f}"


def fmt_rows(rows):
    return [{k: (fmt_num(v) if isinstance(v, float) else v) for k, v in r.items()} for r in rows]


# ------------------------------------------------------------------------------------------
# Error against the float64 dense reference
# ------------------------------------------------------------------------------------------
def reference_grads(scene64, V, K, w, h, v_color):
    s = leaves(scene64, PARAMS)
    out = render_ref(*[s[k] for k in PARAMS], V, K, w, h, pixel_chunk=4096)
    out["color"].backward(v_color.double())
    return out["color"].detach(), out["alpha"].detach(), {k: s[k].grad for k in PARAMS}


def grads_of(render, scene, V, K, w, h, v_color):
    s = leaves(scene, PARAMS)
    col, alpha = render(s, V, K, w, h)
    col.backward(v_color.to(col.dtype))
    return col.detach(), alpha.detach(), {k: s[k].grad for k in PARAMS}


def error_table(args, have_gsplat):
    n, C, w, h = args.err_n, 67, args.err_width, args.err_height
    scene64 = standard_scene(n, C, device="cuda", dtype=torch.float64, seed=3)
    V64, K64 = standard_camera(w, h, device="cuda", dtype=torch.float64)
    v_color = torch.randn(h, w, C, device="cuda", dtype=torch.float64,
                          generator=torch.Generator(device="cuda").manual_seed(2))
    ref_c, ref_a, ref_g = reference_grads(scene64, V64, K64, w, h, v_color)
    rows = []
    cfgs = [("ours float64", ours, torch.float64, None), ("ours float32", ours, torch.float32, None),
            ("ours float32, fp16 channels", ours, torch.float32, torch.float16),
            ("ours float32, bf16 channels", ours, torch.float32, torch.bfloat16)]
    if have_gsplat:
        cfgs.append(("gsplat 1.5.3 float32", gsplat_render, torch.float32, None))
    for name, fn, dt, cdt in cfgs:
        scene = {k: v.to(dt) for k, v in scene64.items()}
        if cdt is not None:
            scene["colors"] = scene["colors"].to(cdt)  # half-precision channel storage
        V, K = V64.to(dt), K64.to(dt)
        try:
            c, a, g = grads_of(fn, scene, V, K, w, h, v_color.to(dt))
        except Exception as exc:  # report, keep going
            rows.append({"config": name, "error": repr(exc)[:80]})
            continue
        r = {"config": name, "color": rel_err(c, ref_c), "alpha": rel_err(a, ref_a)}
        for k in PARAMS:
            r["d_" + k] = rel_err(g[k], ref_g[k]) if g[k] is not None else float("nan")
        rows.append(r)
    return rows, {"N": n, "C": C, "width": w, "height": h}


# ------------------------------------------------------------------------------------------
# Time against error sweep, stage times, tuning knobs, memory floor
# ------------------------------------------------------------------------------------------
def sweep_table(args, err_rows):
    n, C = args.sweep_n, 64
    w, h = args.width, args.height
    rows = []
    errs = {r["config"]: r for r in err_rows}
    for name, dt, cdt in (("ours float64", torch.float64, None), ("ours float32", torch.float32, None),
                          ("ours float32, fp16 channels", torch.float32, torch.float16),
                          ("ours float32, bf16 channels", torch.float32, torch.bfloat16)):
        scene = standard_scene(n, C, device="cuda", dtype=dt)
        if cdt is not None:
            scene["colors"] = scene["colors"].to(cdt)
        V, K = standard_camera(w, h, device="cuda", dtype=dt)
        iters = 3 if dt == torch.float64 else max(5, args.iters // 2)
        f, fb, _, peak = measure(ours, scene, V, K, w, h, iters)
        e = errs.get(name, {})
        rows.append({"config": name, "fwd_ms": f, "fwdbwd_ms": fb, "peak_GiB": peak,
                     "err_color": e.get("color", float("nan")),
                     "err_d_means": e.get("d_means", float("nan")),
                     "err_d_colors": e.get("d_colors", float("nan"))})
        del scene
        torch.cuda.empty_cache()
    return rows


def stage_table(args):
    ops = torch.ops.tiger
    w, h = args.width, args.height
    rows = []
    V, K = standard_camera(w, h, device="cuda")
    for n, C in [(n, C) for n in args.sizes for C in args.channels]:
        s = standard_scene(n, C, device="cuda")
        it = args.iters
        pr = lambda: ops.project_gaussians(s["means"], s["quats"], s["scales"], s["opacities"], V, K,  # noqa: E731
                                           w, h, 0.3, 0.01, 1e10, 1 / 255, False)
        m2, cn, d, op, r = pr()
        bn = lambda: ops.bin_gaussians(m2, cn, op, d, r, w, h, 16, 1 / 255)  # noqa: E731
        to, ids = bn()
        # cb: the kernel's largest float32 channel block (the ops' channel_block; 64 is the default)
        rs = lambda cb=64: ops.rasterize(m2, cn, op, s["colors"], d, None, to, ids, w, h, 16,  # noqa: E731
                                         0.99, 1 / 255, 1e-4, cb)
        col, al, dep, cnt, tr = rs()
        vc = torch.randn_like(col)
        va, vd = torch.zeros_like(al), torch.zeros_like(dep)
        rb = lambda cb=64: ops.rasterize_backward(m2, cn, op, s["colors"], d, None, to, ids, w, h,  # noqa: E731
                                                  16, 0.99, 1 / 255, 1e-4, tr, cnt, vc, va, vd, cb)
        rc = lambda cb=64: ops.rasterize_backward_colors(m2, cn, op, to, ids, w, h, 16, 0.99,  # noqa: E731
                                                         1 / 255, 1e-4, cnt, vc, cb)
        g = rb()
        pb = lambda: ops.project_gaussians_backward(s["means"], s["quats"], s["scales"],  # noqa: E731
                                                    s["opacities"], V, K, r, w, h, 0.3, False,
                                                    g[0][:, :2], g[0][:, 2:5], g[0][:, 6], g[0][:, 5],
                                                    False)
        row = {"N": n, "C": C, "project": cuda_time_ms(pr, it), "bin+sort": cuda_time_ms(bn, it),
               "raster_fwd": cuda_time_ms(rs, it), "raster_bwd": cuda_time_ms(rb, it),
               "feat_bwd": cuda_time_ms(rc, it), "project_bwd": cuda_time_ms(pb, it)}
        for name, fn in (("forward_channel_block", rs), ("backward_channel_block", rb),
                         ("colors_channel_block", rc)):
            for cb in (64, 32):
                row[f"{name}={cb}"] = cuda_time_ms(lambda: fn(cb), it)
        rows.append(row)
        log(fmt_rows([row])[0])
        del s
        torch.cuda.empty_cache()
    return rows


def profile_kernels(args, path: Path) -> None:
    """Per-kernel GPU times of one forward+backward (torch.profiler), ours and gsplat's."""
    from torch.profiler import ProfilerActivity, profile
    w, h = args.width, args.height
    V, K = standard_camera(w, h, device="cuda")
    lines = []
    for n, C in ((args.sizes[0], 3), (args.sizes[-1], 64)):
        scene = standard_scene(n, C, device="cuda")
        v = torch.randn(h, w, C, device="cuda")
        for name, fn in (("ours", ours), ("gsplat", gsplat_render)):
            s = leaves(scene, PARAMS)
            try:
                for _ in range(2):
                    fn(s, V, K, w, h)[0].backward(v)
                torch.cuda.synchronize()
                for t in s.values():
                    t.grad = None
                with profile(activities=[ProfilerActivity.CUDA]) as prof:
                    fn(s, V, K, w, h)[0].backward(v)
                    torch.cuda.synchronize()
            except Exception as exc:  # gsplat may be missing
                lines.append(f"{name} N={n} C={C}: {exc!r}")
                continue
            lines.append(f"== {name}: N={n} C={C} {w}x{h}, one forward+backward")
            lines.append(prof.key_averages().table(sort_by="cuda_time_total", row_limit=14,
                                                   max_name_column_width=70))
    path.write_text("\n".join(lines))


def floor_table(args, speed_rows, bw):
    rows = []
    w, h = args.width, args.height
    for r in speed_rows:
        n, C = r["N"], r["C"]
        bytes_in = n * (3 + 4 + 3 + 1 + C) * 4  # geometry and channels, read once
        bytes_out = h * w * (C + 4) * 4  # color, alpha, depth, transmittance, n_contrib
        floor_ms = (bytes_in + bytes_out) / bw * 1e3
        rows.append({"N": n, "C": C, "MB_moved": (bytes_in + bytes_out) / 1e6,
                     "floor_ms": floor_ms, "ours_fwd_ms": r["ours_fwd"],
                     "x_over_floor": r["ours_fwd"] / floor_ms})
    return rows


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--sizes", type=lambda s: [int(float(x)) for x in s.split(",")],
                   default=[100_000, 1_000_000])
    p.add_argument("--channels", type=lambda s: [int(x) for x in s.split(",")], default=[3, 64, 67])
    p.add_argument("--width", type=int, default=1920)
    p.add_argument("--height", type=int, default=1080)
    p.add_argument("--iters", type=int, default=20)
    p.add_argument("--err-n", type=int, default=3000)
    p.add_argument("--err-width", type=int, default=256)
    p.add_argument("--err-height", type=int, default=144)
    p.add_argument("--sweep-n", type=int, default=1_000_000)
    p.add_argument("--no-gsplat", action="store_true")
    p.add_argument("--skip", default="", help="comma list of sections to skip: speed,error,sweep,stages")
    p.add_argument("--json", type=Path, default=None)
    p.add_argument("--profile", type=Path, default=None, help="write per-kernel times here")
    args = p.parse_args()
    skip = set(filter(None, args.skip.split(",")))
    torch.backends.cuda.matmul.allow_tf32 = False
    have_gsplat = False
    if not args.no_gsplat:
        try:
            import gsplat  # noqa: F401
            from gsplat.cuda._backend import _C  # noqa: F401  (JIT-compiles on first import)
            have_gsplat = _C is not None
            log(f"gsplat {gsplat.__version__} loaded (JIT backend: {have_gsplat})")
        except Exception as exc:  # pragma: no cover - depends on the machine
            log(f"gsplat unavailable: {exc!r}")
    log(f"device: {torch.cuda.get_device_name()}, torch {torch.__version__}")
    bw = cuda_copy_bandwidth()
    log(f"device copy bandwidth: {bw / 1e12:.2f} TB/s (read + write)")
    result = {"bandwidth_TBps": bw / 1e12, "have_gsplat": have_gsplat}

    sections = []
    if "error" not in skip:
        err_rows, err_case = error_table(args, have_gsplat)
        result["error"] = {"case": err_case, "rows": err_rows}
        sections.append((f"Relative error vs float64 reference (N={err_case['N']}, C=67, "
                         f"{err_case['width']}x{err_case['height']}, gradients of <color, random>)",
                         err_rows, None))
        log(table(fmt_rows(err_rows), list(err_rows[0].keys()) if err_rows else []))
    else:
        err_rows = []
    if "stages" not in skip:
        st = stage_table(args)
        result["stages"] = st
        sections.append((f"Our stages ({args.width}x{args.height}), ms; channel-block knobs",
                         st, None))
    if "speed" not in skip:
        sp = speed_table(args, have_gsplat)
        result["speed"] = sp
        sections.append((f"Speed at {args.width}x{args.height}, median ms of {args.iters} "
                         "(feat_bwd: features-only backward; gs_bwd: gsplat full backward; gs_feat_bwd: "
                         "gsplat backward with only colors requiring grad, the like-for-like one), "
                         "peak GiB of one fwd+bwd", sp, None))
        fl = floor_table(args, sp, bw)
        result["floor"] = fl
        sections.append(("Forward memory-traffic floor (inputs read once + outputs written once) "
                         "/ copy bandwidth", fl, None))
    if "sweep" not in skip:
        sw = sweep_table(args, err_rows)
        result["sweep"] = sw
        sections.append((f"Time against error (N={args.sweep_n}, C=64, {args.width}x{args.height};"
                         " errors from the error table's case)", sw, None))
    if args.profile:
        profile_kernels(args, args.profile)
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(result, indent=1, default=float))
    log("")
    for title, rows, _ in sections:
        log("== " + title)
        if rows:
            cols = list(dict.fromkeys(k for r in rows for k in r))
            log(table(fmt_rows(rows), cols))
        log("")


if __name__ == "__main__":
    main()
