"""Rasterizer benchmark: run time against error on the standard scene (or, with
``--scene heavy``, the heavy-tailed scene of tests/render/standard_scenes.py: long-tailed scales and
Gaussians close to the camera, the case that stresses tile binning).

Prints (1) a table over N, resolution and channel count C with forward, forward+backward,
backward alone (every input requiring grad) and features-only backward alone (only the
channels requiring grad) times (medians; the backward receives a fixed upstream gradient
for the colour image, so no loss is timed), tile-Gaussian pairs per second, and the
relative error of the float32 kernels against float64 (the dense reference where
pixels x N fits, else the float64 kernels, which match the reference to ~1e-14); and
(2) a sweep of the accuracy knobs (t_min, alpha threshold, eps2d, half-precision
channels where the device supports them) as a time-against-error table and PNG plot.

    python -m benchmarks.rasterize                 # CPU, full table
    python -m benchmarks.rasterize --device cuda   # same on a GPU
    python -m benchmarks.rasterize --quick         # small subset (smoke run)
    python -m benchmarks.rasterize --scene heavy --n 1e4 --res 512 --channels 3 --no-sweep
"""
from __future__ import annotations

import argparse
import os
from pathlib import Path

import torch

from benchmarks.common import median_time, print_table, rel_err  # noqa: E402
from tests.render.standard_scenes import standard_view  # noqa: E402

import tiger  # noqa: E402
from tiger.render.reference import render_ref  # noqa: E402

REF_LIMIT = 4e7  # pixels x Gaussians up to which the dense float64 reference is run


def render(sc, channels, *, grad_geometry=False, grad_colors=False, dtype=None, **kw):
    cols = sc.colors(channels)
    if dtype is not None:
        cols = cols.to(dtype)
    ins = [sc.means, sc.quats, sc.scales, sc.opacities]
    ins = [t.detach().requires_grad_(grad_geometry) for t in ins]
    cols = cols.detach().requires_grad_(grad_colors)
    out = tiger.rasterize_gaussians(*ins, cols, sc.viewmat, sc.K, sc.width, sc.height,
                                    check_finite=False, **kw)
    return out, ins, cols


def time_case(sc, channels, repeats, cuda):
    """(forward, forward+backward, full backward, features-only backward) in seconds.

    The backward gets a fixed upstream gradient for ``color`` (``color.backward(w)``), so
    no loss computation is timed. The two backward columns time ``backward`` alone, after
    an untimed forward: full = every input requires grad, features-only = only the
    per-Gaussian channels do."""
    def fwd():
        with torch.no_grad():
            return render(sc, channels)[0]
    w = torch.randn(sc.height, sc.width, channels, device=sc.means.device,
                    generator=torch.Generator(device=sc.means.device).manual_seed(1))

    def forward_full():
        return render(sc, channels, grad_geometry=True, grad_colors=True)[0]["color"]

    def forward_features():
        return render(sc, channels, grad_colors=True)[0]["color"]

    def backward(color):
        color.backward(w)

    t_f = median_time(fwd, repeats, cuda=cuda)
    t_fb = median_time(lambda: backward(forward_full()), repeats, cuda=cuda)
    t_b = median_time(backward, repeats, cuda=cuda, setup=forward_full)
    t_bf = median_time(backward, repeats, cuda=cuda, setup=forward_features)
    evals = float(fwd()["n_isects"])  # tile-Gaussian pairs
    return t_f, t_fb, t_b, t_bf, evals


def error_case(sc, channels):
    """float32 kernel error vs float64: (forward color, colour grad, means grad, reference)."""
    sc64 = sc.to(dtype=torch.float64)
    w = torch.randn(sc.height, sc.width, channels, dtype=torch.float64,
                    generator=torch.Generator().manual_seed(1))
    res = []
    for s in (sc, sc64):
        out, ins, cols = render(s, channels, grad_geometry=True, grad_colors=True)
        (out["color"] * w.to(out["color"])).sum().backward()
        res.append((out["color"], cols.grad, ins[0].grad))
    use_ref = sc.width * sc.height * sc.means.shape[0] <= REF_LIMIT
    if use_ref:
        ins = [t.detach().cpu().requires_grad_() for t in
               (sc64.means, sc64.quats, sc64.scales, sc64.opacities, sc64.colors(channels))]
        ref = render_ref(*ins, sc64.viewmat.cpu(), sc64.K.cpu(), sc.width, sc.height,
                         pixel_chunk=4096)
        (ref["color"] * w.cpu()).sum().backward()
        target = (ref["color"], ins[4].grad, ins[0].grad)
    else:
        target = res[1]
    return ([rel_err(a, b) for a, b in zip(res[0], target)], "dense f64" if use_ref else "f64 kernel")


def main_table(args, device):
    cuda = device.type == "cuda"
    rows = []
    for n in args.n:
        for res in args.res:
            sc = standard_view(int(n), res, res, heavy_tailed=args.scene == "heavy").to(device=device)
            for c in args.channels:
                t_f, t_fb, bwd, feat_bwd, evals = time_case(sc, c, args.repeats, cuda)
                errs, ref = error_case(sc, c) if not args.no_error else ([float("nan")] * 3, "-")
                rows.append({"N": int(n), "res": f"{res}x{res}", "C": c,
                             "fwd_ms": 1e3 * t_f, "fwd+bwd_ms": 1e3 * t_fb, "bwd_ms": 1e3 * bwd,
                             "feat_bwd_ms": 1e3 * feat_bwd, "full/feat_bwd": bwd / max(feat_bwd, 1e-9),
                             "isects": int(evals), "isect_px/s": evals * 256 / t_f,
                             "err_fwd": errs[0], "err_gcol": errs[1], "err_gmean": errs[2],
                             "vs": ref})
    return print_table(rows, f"rasterize on {device} ({torch.get_num_threads()} threads), float32, "
                             f"{args.scene} scene")


def sweep(args, device):
    """Time against error for each accuracy knob, one varied at a time."""
    cuda = device.type == "cuda"
    n, res, c = args.sweep_n, args.sweep_res, 3
    sc = standard_view(n, res, res, heavy_tailed=args.scene == "heavy").to(device=device)
    sc64 = sc.to(dtype=torch.float64)
    exact = dict(t_min=0.0, alpha_threshold=1e-7, eps2d=0.3)
    with torch.no_grad():
        target = render(sc64, c, **exact)[0]["color"]
    knobs = [("t_min", v) for v in (0.0, 1e-4, 1e-3, 1e-2)]
    knobs += [("alpha_threshold", v) for v in (1e-7, 1 / 255, 4 / 255, 16 / 255)]
    knobs += [("eps2d", v) for v in (0.1, 0.3, 1.0)]
    half = [torch.float16, torch.bfloat16] if cuda else []
    rows = []
    for name, value in knobs + [("channels", d) for d in half]:
        kw = dict(t_min=1e-4, alpha_threshold=1 / 255, eps2d=0.3)
        dtype = None
        if name == "channels":
            dtype = value
        else:
            kw[name] = value
        w = torch.randn(res, res, c, device=device, generator=torch.Generator(device=device).manual_seed(2))

        def step():
            out, ins, _ = render(sc, c, grad_geometry=True, grad_colors=True, dtype=dtype, **kw)
            (out["color"].float() * w).sum().backward()
        t = median_time(step, args.repeats, cuda=cuda)
        with torch.no_grad():
            img = render(sc, c, dtype=dtype, **kw)[0]["color"]
        rows.append({"knob": name, "value": str(value).replace("torch.", ""),
                     "fwd+bwd_ms": 1e3 * t, "err_vs_exact": rel_err(img, target)})
    text = print_table(rows, f"accuracy knobs, N={n} {res}x{res} C={c} on {device} "
                             "(error vs float64 with t_min=0, alpha_threshold=1e-7)")
    if args.plot:
        plot_sweep(rows, Path(args.plot))
    return text


def plot_sweep(rows, path: Path):
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    fig, ax = plt.subplots(figsize=(6.5, 4.5))
    for knob in dict.fromkeys(r["knob"] for r in rows):
        pts = [r for r in rows if r["knob"] == knob]
        ax.plot([p["fwd+bwd_ms"] for p in pts], [max(p["err_vs_exact"], 1e-9) for p in pts],
                "o-", label=knob)
        for p in pts:
            ax.annotate(p["value"][:8], (p["fwd+bwd_ms"], max(p["err_vs_exact"], 1e-9)),
                        fontsize=7, xytext=(3, 3), textcoords="offset points")
    ax.set_xlabel("forward + backward time [ms]")
    ax.set_ylabel("relative error vs exact float64 render")
    ax.set_yscale("log")
    ax.set_title("TIGER rasterizer: time against error")
    ax.legend(fontsize=8)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp.png")
    fig.savefig(tmp, dpi=120)
    os.replace(tmp, path)
    print(f"wrote {path}")


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--device", default="cpu")
    p.add_argument("--scene", choices=["standard", "heavy"], default="standard")
    p.add_argument("--n", type=float, nargs="+", default=[1e3, 1e4, 1e5])
    p.add_argument("--res", type=int, nargs="+", default=[128, 512, 800])
    p.add_argument("--channels", type=int, nargs="+", default=[3, 64, 67])
    p.add_argument("--repeats", type=int, default=5)
    p.add_argument("--no-error", action="store_true", help="skip the float64 error columns")
    p.add_argument("--sweep-n", type=int, default=100_000)
    p.add_argument("--sweep-res", type=int, default=512)
    p.add_argument("--no-sweep", action="store_true")
    p.add_argument("--no-table", action="store_true")
    p.add_argument("--plot", default="outputs/benchmarks/rasterize_sweep.png")
    p.add_argument("--quick", action="store_true", help="N=1e3,1e4 at 128/256, 2 repeats")
    args = p.parse_args(argv)
    if args.quick:
        args.n, args.res, args.repeats = [1e3, 1e4], [128, 256], 2
        args.sweep_n, args.sweep_res = 10_000, 256
    device = torch.device(args.device)
    if not args.no_table:
        main_table(args, device)
    if not args.no_sweep:
        sweep(args, device)


if __name__ == "__main__":
    main()
