"""A small end-to-end CUDA workload for compute-sanitizer (memcheck / racecheck).

Exercises every CUDA op of the rendering core once per configuration: projection (and its
backward with camera gradients), SH, binning, rasterize forward, full backward and the
features-only backward, for float32, float64 and float16/bfloat16 channel storage, with
channel counts that hit single, main+tail and masked channel blocks, and a partial edge tile;
then the training loss's fused SSIM (forward and backward, ragged tiles, two window radii);
then a batched render of ``--views`` stacked views (binning of both paths and rasterization with
views=V, full and features-only backward; ``--views-only`` runs just that part).

    compute-sanitizer --tool memcheck python -m benchmarks.gpu.sanitize_case --views 3
    compute-sanitizer --tool racecheck python -m benchmarks.gpu.sanitize_case --views 3 --views-only
"""
from __future__ import annotations

import argparse

import torch

from tests.render.standard_scenes import heavy_tailed_scene, standard_camera, standard_scene  # noqa: E402

import tiger  # noqa: E402


def run(n: int, C: int, dtype: torch.dtype, cdtype: torch.dtype | None, sh: int | None,
        features_only: bool, w: int = 50, h: int = 37) -> None:
    s = standard_scene(n, C, device="cuda", dtype=dtype, seed=C)
    s["scales"] = s["scales"] * 6  # a few tiles per Gaussian at this small size
    V, K = standard_camera(w, h, device="cuda", dtype=dtype)
    V[:3, 3] = torch.tensor([0.2, -0.1, 3.0], dtype=dtype)
    if sh is not None:
        s["colors"] = 0.3 * torch.randn(n, (sh + 1) ** 2, 3, device="cuda", dtype=dtype)
    if cdtype is not None:
        s["colors"] = s["colors"].to(cdtype)
    grad = ("colors",) if features_only else ("means", "quats", "scales", "opacities", "colors")
    leaves = {k: v.detach().clone().requires_grad_(k in grad) for k, v in s.items()}
    Vl = V.clone().requires_grad_(not features_only)
    Kl = K.clone().requires_grad_(not features_only)
    bg = torch.rand(3 if sh is not None else C, device="cuda", dtype=dtype)
    out = tiger.rasterize_gaussians(leaves["means"], leaves["quats"], leaves["scales"],
                                    leaves["opacities"], leaves["colors"], Vl, Kl, w, h,
                                    background=bg, sh_degree=sh)
    loss = (out["color"] * torch.randn_like(out["color"])).sum()
    if not features_only:
        loss = loss + out["alpha"].sum() + out["depth"].sum()
    loss.backward()
    torch.cuda.synchronize()
    for k in grad:
        g = leaves[k].grad
        assert g is not None and bool(torch.isfinite(g.float()).all()), k
    print(f"ok n={n} C={C} {dtype} colors={cdtype} sh={sh} features_only={features_only} "
          f"isects={out['n_isects']}", flush=True)


def run_heavy_binning(n: int, w: int, h: int, dtype: torch.dtype) -> None:
    """Load-balanced binning on a heavy-tailed scene (Gaussians spanning the whole image, many
    culled ones): the lists must equal the former one-thread-per-Gaussian binning's."""
    s = heavy_tailed_scene(n, 3, device="cuda", dtype=dtype, seed=5)
    V, K = standard_camera(w, h, device="cuda", dtype=dtype)
    ops = torch.ops.tiger
    m2, cn, d, op, r = ops.project_gaussians(s["means"], s["quats"], s["scales"], s["opacities"],
                                             V, K, w, h, 0.3, 0.01, 1e10, 1 / 255, False)
    a = ops.bin_gaussians(m2, cn, op, d, r, w, h, 16, 1 / 255)
    b = ops.bin_gaussians(m2, cn, op, d, r, w, h, 16, 1 / 255, _serial=True)
    torch.cuda.synchronize()
    assert torch.equal(a[0], b[0]) and torch.equal(a[1], b[1]), "balanced != serial binning"
    print(f"ok heavy binning n={n} {w}x{h} {dtype} isects={a[1].numel()} "
          f"culled={int((r[:, 0] == 0).sum())}", flush=True)


def run_ssim(shape: tuple, taps: int, dtype: torch.dtype) -> None:
    from tiger.ops.ssim import fused_ssim
    from tiger.utils.filters import gaussian_taps

    g = torch.Generator(device="cuda").manual_seed(3)
    x = torch.rand(shape, device="cuda", dtype=dtype, generator=g).requires_grad_()
    y = torch.rand(shape, device="cuda", dtype=dtype, generator=g)
    m = fused_ssim(x, y, gaussian_taps(taps, 1.5).tolist(), 1e-4, 9e-4)
    m.backward(torch.rand_like(m))
    torch.cuda.synchronize()
    assert torch.isfinite(x.grad).all()
    print(f"ok fused ssim {shape} taps={taps} {dtype}", flush=True)


def run_sh_split(n: int, degree: int) -> None:
    """The SH op reading a DC block and a (strided) slice of the higher bands in place."""
    from tiger.ops.sh import sh_to_color

    g = torch.Generator(device="cuda").manual_seed(degree)
    dirs = torch.randn(n, 3, device="cuda", generator=g)
    dc = torch.randn(n, 3, device="cuda", generator=g).requires_grad_()
    rest = torch.randn(n, 15, 3, device="cuda", generator=g).requires_grad_()
    vis = torch.rand(n, device="cuda", generator=g) > 0.3
    y = sh_to_color(dirs, dc[:, None], degree, vis, rest[:, : (degree + 1) ** 2 - 1])
    y.backward(torch.ones_like(y))
    torch.cuda.synchronize()
    print(f"ok sh split n={n} degree={degree}", flush=True)


def run_views(views: int, n: int, C: int, dtype: torch.dtype, path: str, features_only: bool,
              w: int = 70, h: int = 45) -> None:
    """views=V binning and rasterization (forward, backward) of V projections of one scene, a
    few Gaussians covering whole images (the warp and block walkers of the binning); every view
    must equal its own views=1 render."""
    from tiger.ops.binning import BinningSettings, bin_gaussians
    from tiger.ops.raster import rasterize

    s = heavy_tailed_scene(n, C, device="cuda", dtype=dtype, seed=11)
    ops = torch.ops.tiger
    per_view = []
    for v in range(views):
        V, K = standard_camera(w, h, device="cuda", dtype=dtype)
        V[:3, 3] += torch.tensor([0.1 * v, -0.05 * v, 0.0], device="cuda", dtype=dtype)
        per_view.append(ops.project_gaussians(s["means"], s["quats"], s["scales"], s["opacities"],
                                              V, K, w, h, 0.3, 0.01, 1e10, 1 / 255, False))
    m2, cn, d, op, r = [torch.cat([p[i] for p in per_view]) for i in range(5)]
    settings = BinningSettings(path=path, giant_tiles=8)  # block walks at this small size
    to, ids = bin_gaussians(m2, cn, op, d, r, w, h, 16, 1 / 255, settings, views=views)
    cols = s["colors"].repeat(views, 1)
    bg = torch.rand(C, device="cuda", dtype=dtype)
    leaves = [t.detach().clone().requires_grad_(not features_only or k in (3, 5))
              for k, t in enumerate((m2, cn, op, cols, d, bg))]
    color, alpha, depth, _, _ = rasterize(*leaves[:5], leaves[5], to, ids, w, h, 16, 0.99, 1 / 255,
                                          1e-4, views=views)
    loss = (color * torch.randn_like(color)).sum()
    if not features_only:
        loss = loss + alpha.sum() + depth.sum()
    loss.backward()
    torch.cuda.synchronize()
    nv = m2.shape[0] // views
    for v, p in enumerate(per_view):
        one_to, one_ids = bin_gaussians(p[0], p[1], p[3], p[2], p[4], w, h, 16, 1 / 255, settings)
        one = rasterize(p[0], p[1], p[3], cols[v * nv:(v + 1) * nv], p[2], bg, one_to, one_ids, w, h, 16,
                        0.99, 1 / 255, 1e-4)
        assert torch.equal(color.detach()[v * h:(v + 1) * h], one[0]), f"view {v} differs from its own render"
    for k, t in enumerate(leaves):
        if t.grad is not None:
            assert bool(torch.isfinite(t.grad.float()).all()), k
    print(f"ok views={views} n={n} C={C} {dtype} path={path} features_only={features_only} "
          f"isects={ids.numel()}", flush=True)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--views", type=int, default=3, help="stacked views of the batched case")
    ap.add_argument("--views-only", action="store_true", help="run only the batched-views case")
    args = ap.parse_args()
    assert tiger.ops.cuda_enabled() and torch.cuda.is_available()
    for path in ("tiles", "global"):
        for C, dtype in ((3, torch.float32), (67, torch.float32), (5, torch.float64)):
            run_views(args.views, 200, C, dtype, path, False)
        run_views(args.views, 200, 3, torch.float32, path, True)
    if args.views_only:
        return
    for n, degree in ((200, 3), (130, 2), (5, 1)):
        run_sh_split(n, degree)
    for shape, taps, dtype in (((1, 3, 37, 70), 11, torch.float32), ((2, 2, 19, 33), 5, torch.float32),
                               ((1, 3, 21, 45), 11, torch.float64), ((1, 1, 3, 2), 11, torch.float32)):
        run_ssim(shape, taps, dtype)
    for C in (3, 67, 40):
        run(400, C, torch.float32, None, None, False)
        run(400, C, torch.float32, None, None, True)
    run(400, 64, torch.float32, torch.float16, None, False)
    run(400, 17, torch.float32, torch.bfloat16, None, True)
    run(300, 12, torch.float64, None, None, False)
    run(300, 12, torch.float64, None, None, True)
    run(300, 3, torch.float32, None, 3, False)
    run(0, 3, torch.float32, None, None, False)
    run_heavy_binning(600, 200, 150, torch.float32)
    run_heavy_binning(300, 97, 61, torch.float64)
    # 1280x720: Gaussians for one warp each and some beyond the block threshold (512 candidate
    # tiles: one block each, the shared-memory walk racecheck must see)
    run_heavy_binning(1500, 1280, 720, torch.float32)


if __name__ == "__main__":
    main()
