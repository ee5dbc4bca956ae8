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
at ``--density`` with SH degree 3, V orbit cameras of ``--size`` px around it, SH colour,
forward + backward into every scene tensor: render_views (the CPU bins and rasterizes the V
views in one call each; CUDA draws them one by one) against a loop of GaussianScene.render,
with the largest output and gradient differences.

    python -m benchmarks.render_views               # CPU
    python -m benchmarks.render_views --device cuda
    python -m benchmarks.render_views --edit --density 1 --size 128 --views 8            # CPU
    python -m benchmarks.render_views --edit --density 16 --size 512 --views 8 --device cuda
"""
from __future__ import annotations

import argparse
import statistics
import time

import torch

from benchmarks.common import median_time, print_table  # noqa: E402
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


def run_edit(density: float, size: int, views: int, device: str, repeats: int) -> dict:
    """The edit step's render stage: render_views of V cameras vs V GaussianScene.render calls."""
    from benchmarks.edit import demo_scene
    from tiger.render.views import orbit_cameras_around

    scene, _ = demo_scene(density, device)
    scene.lang = None
    cams = [c.to(device) for c in orbit_cameras_around(scene.means, views, size, size, elevation_deg=20.0)]
    upstream = torch.rand(views, size, size, 3, device=device,
                          generator=torch.Generator(device=device).manual_seed(1))

    def leaves():
        scene.parameter_groups()

    def loop(_=None):
        for v, cam in enumerate(cams):
            (scene.render(cam, check_finite=False)["color"] * upstream[v]).sum().backward()

    def batched(_=None):
        (render_views(scene, cams, check_finite=False)["color"] * upstream).sum().backward()

    if device == "cuda":
        t_loop = median_time(loop, repeats=repeats, cuda=True, setup=leaves)
        t_views = median_time(batched, repeats=repeats, cuda=True, setup=leaves)
    else:  # alternate the two, so that a shared machine's changing load hits both alike
        times: dict = {loop: [], batched: []}
        for fn in (loop, batched):  # warm-up
            leaves()
            fn()
        for _ in range(repeats):
            for fn in (loop, batched):
                leaves()
                t0 = time.perf_counter()
                fn()
                times[fn].append(time.perf_counter() - t0)
        t_loop, t_views = (statistics.median(times[f]) for f in (loop, batched))
    leaves()
    with torch.no_grad():
        ref = torch.stack([scene.render(cam)["color"] for cam in cams])
    loop()
    g_loop = {k: t.grad.clone() for k, t in scene.params().items()}
    leaves()
    out = render_views(scene, cams)
    (out["color"] * upstream).sum().backward()
    rel = max(float((t.grad - g_loop[k]).abs().max() / g_loop[k].abs().max().clamp_min(1e-30))
              for k, t in scene.params().items())
    return {"N": len(scene), "px": f"{size}x{size}", "V": views, "loop ms": 1e3 * t_loop,
            "render_views ms": 1e3 * t_views, "speed-up": t_loop / t_views,
            "isects/view": int(out["n_isects"].float().mean()),
            "max|out diff|": float((out["color"].detach() - ref).abs().max()), "max rel grad diff": rel}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--edit", action="store_true", help="time the edit loop's render stage instead")
    ap.add_argument("--density", type=float, default=1.0, help="--edit: demo scene density (16 = the edit benchmark's)")
    ap.add_argument("--size", type=int, default=128, help="--edit: image width and height (px)")
    ap.add_argument("--views", type=int, default=8, help="--edit: cameras per render")
    args = ap.parse_args()
    if args.edit:
        print_table([run_edit(args.density, args.size, args.views, args.device, args.repeats)],
                    f"edit render stage: render_views vs a loop of render, forward + backward ({args.device})")
        return
    cases = [(20000, 128, 3, 4)] if args.quick else [(20000, 128, 3, 4), (100000, 256, 3, 4), (100000, 256, 64, 4)]
    print_table([run(*c, args.device, args.repeats) for c in cases],
                f"render path vs raw rasterizer calls, forward + backward ({args.device})")


if __name__ == "__main__":
    main()
