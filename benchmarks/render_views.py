"""The scene render path against hand-written rasterizer calls: overhead and batching.

An editing step renders V = 4 views of a scene with per-Gaussian colours and back-propagates
into the scene's tensors and the colours. Timed (forward + backward, medians), on the
standard scene and four orbit cameras:

  raw          V calls of tiger.rasterize_gaussians on tensors activated per call
  render       V calls of GaussianScene.render(camera, colors)
  render_views one render_views(scene, cameras, colors) call (activations once, stacked out)

and the largest difference of render_views' outputs and gradients from the raw calls
(0 = bit-identical; gradients are summed over views in another order, so a few ulp).

    python -m benchmarks.render_views               # CPU
    python -m benchmarks.render_views --device cuda
"""
from __future__ import annotations

import argparse

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


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--quick", action="store_true")
    args = ap.parse_args()
    cases = [(20000, 128, 3, 4)] if args.quick else [(20000, 128, 3, 4), (100000, 256, 3, 4), (100000, 256, 64, 4)]
    print_table([run(*c, args.device, args.repeats) for c in cases],
                f"render path vs raw rasterizer calls, forward + backward ({args.device})")


if __name__ == "__main__":
    main()
