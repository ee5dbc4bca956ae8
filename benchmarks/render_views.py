"""The scene render path against hand-written rasterizer calls: overhead and batching.

An editing step renders V = 4 views of a scene with per-Gaussian colours and back-propagates
into the scene's tensors and the colours. Timed (forward + backward, medians), on the
standard scene and four orbit cameras:

  raw          V calls of tiger.rasterize_gaussians on tensors activated per call
  render       V calls of GaussianScene.render(camera, colors)
  render_views one render_views(scene, cameras, colors) call (activations once, stacked out)

and the largest difference of render_views' outputs and gradients from the raw calls
(0 = bit-identical; gradients are summed over views in another order, so a few ulp).

``--edit``: the edit loop's render stage instead: the demo tabletop of ``benchmarks/edit.py``
at ``--density`` (16: the edit benchmark's 317,600 Gaussians) with SH degree 3, V orbit cameras
of ``--size`` px around it, SH colour: render_views (one binning and one rasterization of the V
stacked views, CPU and CUDA) against a loop of GaussianScene.render, forward and backward (into
every scene tensor) timed apart; the edit step's own stage (half the views as originals with
the footprint channel, half with gradient); the largest output difference from the per-view
renders (0: bit-identical) and relative gradient difference (atomics' order on CUDA); and the
backward with ``trainable`` = the ball's Gaussians (what the edit optimises: no gradient work for
the frozen ones) and the edit's kernel choices (``tiger.edit.loop.EDIT_RASTER_KERNELS``: one pixel
per backward thread), its editable gradients against the full backward's and its frozen ones (0).

    python -m benchmarks.render_views               # CPU
    python -m benchmarks.render_views --device cuda
    python -m benchmarks.render_views --edit --density 1 --size 128 --views 8            # CPU
    python -m benchmarks.render_views --edit --density 16 --size 512 --views 8 --device cuda

On CUDA ``--edit`` also times the rasterizer's kernels of the edit's render under each kernel
choice (tile order x pixels per backward thread) on the edit's own cameras and on orbit cameras
(the evidence for ``tiger.edit.loop.EDIT_RASTER_KERNELS`` and the tile order's default).
"""
from __future__ import annotations

import argparse
import contextlib
import statistics
import time

import torch

from benchmarks.common import cpu_time_ms, cuda_kernel_names, cuda_time_ms, median_time, print_table  # noqa: E402
from tests.render.standard_scenes import standard_scene  # noqa: E402

import tiger  # noqa: E402
from tiger.render.views import orbit_cameras  # noqa: E402
from tiger.scene import GaussianScene, render_views  # noqa: E402
from tiger.scene.gaussian_scene import inverse_sigmoid  # noqa: E402
from tiger.scene.sh import rgb_to_sh  # noqa: E402


def scene_of(n: int, channels: int, device: str) -> tuple[GaussianScene, torch.Tensor]:
    s = standard_scene(n, 3 + channels, device=device)
    scene = GaussianScene(s["means"], s["scales"].log(), s["quats"], inverse_sigmoid(s["opacities"]),
                          rgb_to_sh(s["colors"][:, :3]))
    return scene, s["colors"][:, 3:].contiguous()


def run(n: int, size: int, channels: int, views: int, device: str, repeats: int) -> dict:
    scene, cols = scene_of(n, channels, device)
    cams = [c.to(device) for c in orbit_cameras(views, size, size, radius=3.5, elevation_deg=20.0)]
    upstream = torch.randn(views, size, size, channels, device=device,
                           generator=torch.Generator(device=device).manual_seed(1))

    def leaves():
        scene.parameter_groups(names=["means", "log_scales", "quats", "opacity_logits"])
        return cols.detach().clone().requires_grad_(True)

    def raw(c):
        for v, cam in enumerate(cams):
            out = tiger.rasterize_gaussians(scene.means, scene.quats, torch.exp(scene.log_scales),
                                            torch.sigmoid(scene.opacity_logits), c,
                                            cam.viewmat.to(device, torch.float32),
                                            cam.K.to(device, torch.float32), size, size)
            (out["color"] * upstream[v]).sum().backward()

    def per_camera(c):
        for v, cam in enumerate(cams):
            (scene.render(cam, c)["color"] * upstream[v]).sum().backward()

    def batched(c):
        (render_views(scene, cams, c)["color"] * upstream).sum().backward()

    cuda = device == "cuda"
    times = {name: median_time(fn, repeats=repeats, cuda=cuda, setup=leaves)
             for name, fn in (("raw", raw), ("render", per_camera), ("render_views", batched))}
    # agreement: outputs and gradients of render_views against the raw calls
    c1 = leaves()
    raw(c1)
    g_raw = [scene.means.grad.clone(), c1.grad.clone()]
    with torch.no_grad():
        ref = torch.stack([tiger.rasterize_gaussians(scene.means, scene.quats, scene.scales, scene.opacities,
                                                     c1, cam.viewmat.to(device, torch.float32),
                                                     cam.K.to(device, torch.float32), size, size)["color"]
                           for cam in cams])
    c2 = leaves()
    out = render_views(scene, cams, c2)
    (out["color"] * upstream).sum().backward()
    rel = lambda a, b: float((a - b).abs().max() / b.abs().max().clamp_min(1e-30))  # noqa: E731
    return {"N": n, "px": f"{size}x{size}", "C": channels, "V": views,
            "raw ms": 1e3 * times["raw"], "render ms": 1e3 * times["render"],
            "render_views ms": 1e3 * times["render_views"],
            "render/raw": times["render"] / times["raw"], "views/raw": times["render_views"] / times["raw"],
            "max|out diff|": float((out["color"].detach() - ref).abs().max()),
            "rel grad diff means": rel(scene.means.grad, g_raw[0]),
            "rel grad diff colors": rel(c2.grad, g_raw[1])}


def _stage_timer(device: str, repeats: int):
    """time(fn, setup) -> median ms of fn(setup()) (setup untimed): CUDA events on CUDA, wall
    clock on the CPU."""
    if device == "cuda":
        return lambda fn, setup: cuda_time_ms(fn, iters=repeats, warmup=2, setup=setup)
    return lambda fn, setup: cpu_time_ms(fn, iters=repeats, warmup=1, setup=setup)


def run_edit(density: float, size: int, views: int, device: str, repeats: int,
             binning_path: str = "auto") -> list[dict]:
    """The edit step's render stage: V views of the edit scene (SH degree 3, full SH colour),
    render_views (one projection per view, then ONE binning and ONE rasterization of the V
    stacked views, forward and backward) against a loop of V GaussianScene.render calls;
    forward and backward timed apart; plus the edit loop's own stage (half the views rendered
    as originals with the footprint channel, no gradient; half with gradient)."""
    from benchmarks.edit import demo_scene
    from tiger.edit.loop import EDIT_RASTER_KERNELS
    from tiger.ops.binning import BinningSettings
    from tiger.render.views import orbit_cameras_around
    from tiger.scene import render_rgb

    scene, query = demo_scene(density, device)
    editable = (scene.lang @ query) > 0.5  # the ball's Gaussians: what the edit optimises
    scene.lang = None
    cams = [c.to(device) for c in orbit_cameras_around(scene.means, views, size, size, elevation_deg=20.0)]
    upstream = torch.rand(views, size, size, 3, device=device,
                          generator=torch.Generator(device=device).manual_seed(1))
    time_ms = _stage_timer(device, repeats)
    opts = {"check_finite": False, "binning": BinningSettings(path=binning_path)}

    def leaves():
        scene.parameter_groups()

    def forward_loop(_=None):
        return [scene.render(cam, **opts) for cam in cams]

    def forward_batched(_=None):
        return render_views(scene, cams, **opts)

    def loss_loop():
        leaves()
        return sum((o["color"] * upstream[v]).sum() for v, o in enumerate(forward_loop()))

    def loss_batched():
        leaves()
        return (forward_batched()["color"] * upstream).sum()

    def loss_batched_editable():  # the edit's render: the editable Gaussians only, its kernel choices
        leaves()
        return (render_views(scene, cams, trainable=editable, kernels=EDIT_RASTER_KERNELS, **opts)["color"]
                * upstream).sum()

    def backward(loss):
        loss.backward()

    t = {"fwd loop": time_ms(forward_loop, leaves), "fwd batched": time_ms(forward_batched, leaves),
         "bwd loop": time_ms(backward, loss_loop), "bwd batched": time_ms(backward, loss_batched),
         "bwd batched editable": time_ms(backward, loss_batched_editable)}

    # the edit loop's render stage: originals (footprint channel, no gradient) + current views
    half = max(views // 2, 1)
    footprint = (torch.arange(len(scene), device=device) % 8 == 0).float()
    bg = torch.zeros(3, device=device)

    def stage_batched(_=None):
        render_rgb(scene, cams[:half], bg, footprint=footprint)
        return render_views(scene, cams[half:], "rgb", background=bg, **opts)

    def stage_loop(_=None):
        for cam in cams[:half]:
            render_rgb(scene, [cam], bg, footprint=footprint)
        return [scene.render(cam, "rgb", background=bg, **opts) for cam in cams[half:]]

    t["stage loop"] = time_ms(stage_loop, leaves)
    t["stage batched"] = time_ms(stage_batched, leaves)

    # agreement: every output of render_views against the per-view renders, and the gradients
    leaves()
    with torch.no_grad():
        ref = forward_loop()
        out = forward_batched()
    diff = max(float((out[k][v] - ref[v][k]).abs().max()) for v in range(views)
               for k in ("color", "alpha", "depth"))
    loss_loop().backward()
    g_loop = {k: p.grad.clone() for k, p in scene.params().items()}
    loss_batched().backward()
    rel = max(float((p.grad - g_loop[k]).abs().max() / g_loop[k].abs().max().clamp_min(1e-30))
              for k, p in scene.params().items())
    loss_batched_editable().backward()  # editable rows as the full backward's, the rest zero
    rel_editable = max(float((p.grad[editable] - g_loop[k][editable]).abs().max()
                             / g_loop[k][editable].abs().max().clamp_min(1e-30)) for k, p in scene.params().items())
    frozen_max = max(float(p.grad[~editable].abs().max()) for p in scene.params().values())
    row = {"device": device, "binning": binning_path, "N": len(scene), "editable": int(editable.sum()),
           "px": f"{size}x{size}",
           "V": views, "isects/view": int(out["n_isects"].float().mean())}
    row.update({f"{k} ms": v for k, v in t.items()})
    row.update({"fwd speed-up": t["fwd loop"] / t["fwd batched"],
                "bwd speed-up": t["bwd loop"] / t["bwd batched"],
                "max|out diff|": diff, "max rel grad diff": rel,
                "max rel grad diff editable": rel_editable, "max|frozen grad|": frozen_max})
    return [row]


def raster_kernel_ms(fn, reps: int) -> dict[str, float]:
    """GPU ms per ``fn()`` call of the rasterizer's forward and backward kernels and of every other
    kernel (torch.profiler, after two warm-up calls)."""
    out = {"raster fwd ms": 0.0, "raster bwd ms": 0.0, "other kernels ms": 0.0}
    for name, ms in cuda_kernel_names(fn, reps):
        raster = "raster_cuda::" in name
        key = ("raster fwd ms" if raster and "forward_kernel" in name else
               "raster bwd ms" if raster and "backward" in name else "other kernels ms")
        out[key] += ms / reps
    return out


def run_kernel_choices(density: float, size: int, repeats: int) -> list[dict]:
    """CUDA: the edit step's render (4 views with gradient, editable backward) under each raster
    kernel choice the edit could take (tile order, pixels per backward thread, warp cull), on the edit's own
    cameras (8 sets of tiger.edit's ObjectViews at the EditConfig defaults, drawn with a fixed
    generator: the object fills the view) and on 4 orbit cameras around the whole scene (the
    object small in the view); GPU kernel ms per render + backward (profiler)."""
    from benchmarks.edit import demo_scene
    from tiger.edit import EditConfig
    from tiger.edit.target import resolve_target
    from tiger.edit.views import ObjectViews
    from tiger.ops.raster import RasterKernelSettings
    from tiger.render.views import orbit_cameras_around

    scene, query = demo_scene(density, "cuda")
    tgt = resolve_target(scene, query, tau=0.5)
    editable = tgt.mask
    scene.lang = None
    cfg = EditConfig(width=size, height=size)
    views = ObjectViews(tgt.center, tgt.bbox_min, tgt.bbox_max, n_views=cfg.n_views, width=size, height=size,
                        fov_deg=cfg.fov_deg, elevation_deg=cfg.elevation_deg, fill=cfg.fill, force_360=True)
    gen = torch.Generator().manual_seed(0)
    camera_sets = {"edit views": [[c.to("cuda") for c in views.sample(gen)] for _ in range(8)],
                   "orbit": [[c.to("cuda") for c in orbit_cameras_around(scene.means, 4, size, size,
                                                                       elevation_deg=20.0)]]}
    upstream = torch.rand(4, size, size, 3, device="cuda", generator=torch.Generator(device="cuda").manual_seed(1))
    rows = []
    # (tile order, pixels per backward thread, warp cull): the edit's choice with and without the
    # cull, the library default with and without it, and the choices of two rounds before
    choices = [("heavy_first", 1, True), ("heavy_first", 1, False), ("heavy_first", 2, True),
               ("heavy_first", 2, False), ("index", 2, False)]
    for cams_name, sets in camera_sets.items():
        for (order, ppt, cull), sh_calls in [(c, "one") for c in choices] + [(choices[0], "per view")]:
            k = RasterKernelSettings(tile_order=order, backward_pixels_per_thread=ppt, warp_cull=cull)

            def step():
                for cams in sets:
                    scene.parameter_groups()
                    out = render_views(scene, cams, "rgb", trainable=editable, check_finite=False, kernels=k)
                    (out["color"] * upstream).sum().backward()
            with sh_call_per_view(sh_calls == "per view"):
                t = raster_kernel_ms(step, repeats)
            rows.append({"cameras": cams_name, "tile_order": order, "bwd px/thread": ppt, "warp cull": cull,
                         "SH calls": sh_calls, **{key: v / len(sets) for key, v in t.items()}})
    return rows


@contextlib.contextmanager
def sh_call_per_view(enabled: bool):
    """Within: render_views projects and evaluates the SH colours of each view with its own call
    (the one-view case of its projection step, bit-identical to the previous rounds' per-view
    path), so the same build times one SH call for all views against one per view."""
    import tiger.scene.gaussian_scene as gs

    batched = gs._project_each
    if enabled:
        gs._project_each = lambda scene, cameras, *a, **kw: [p for cam in cameras for p in batched(scene, [cam], *a, **kw)]
    try:
        yield
    finally:
        gs._project_each = batched


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--edit", action="store_true", help="time the edit loop's render stage instead")
    ap.add_argument("--density", type=float, default=1.0, help="--edit: demo scene density (16 = the edit benchmark's)")
    ap.add_argument("--size", type=int, default=128, help="--edit: image width and height (px)")
    ap.add_argument("--views", type=int, default=8, help="--edit: cameras per render")
    ap.add_argument("--binning-path", default="auto", choices=("auto", "tiles", "global"),
                    help="--edit: the CUDA binning path of the timed renders (same lists; auto: by Gaussian count)")
    args = ap.parse_args()
    if args.edit:
        rows = run_edit(args.density, args.size, args.views, args.device, args.repeats, args.binning_path)
        print_table([{k: r[k] for k in list(r)[:7]} | {k: r[k] for k in r if k.startswith(("fwd", "bwd"))}
                     for r in rows], f"edit scene, {args.views} views: render_views (batched) vs a loop of "
                                     f"render, forward and backward apart ({args.device}, ms)")
        print_table([{k: r[k] for k in ("device", "V")} | {k: r[k] for k in r if k.startswith(("stage", "max"))}
                     for r in rows], "the edit step's render stage (half originals + footprint, half with "
                                     "gradient; ms) and the batched render's error vs per-view renders")
        if args.device.startswith("cuda"):
            print_table(run_kernel_choices(args.density, args.size, args.repeats),
                        "the edit's render + editable backward (4 views) under each raster kernel choice: "
                        "GPU kernel ms per render (profiler)")
        return
    cases = [(20000, 128, 3, 4)] if args.quick else [(20000, 128, 3, 4), (100000, 256, 3, 4), (100000, 256, 64, 4)]
    print_table([run(*c, args.device, args.repeats) for c in cases],
                f"render path vs raw rasterizer calls, forward + backward ({args.device})")


if __name__ == "__main__":
    main()
