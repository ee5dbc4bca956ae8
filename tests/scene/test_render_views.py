"""The one render path: GaussianScene.render with any colours, and render_views over V cameras."""
from __future__ import annotations

from collections import Counter

import pytest
import torch
from torch.utils._python_dispatch import TorchDispatchMode

import tiger
from tiger.render.reference import sh_to_color_ref
from tiger.ops.sh import sh_to_color
from tiger.render import Camera, camera_center
from tiger.scene import GaussianScene, render_rgb, render_view_chunks, render_views
from tiger.scene.cameras import intrinsics

from ..render.devices import DEVICES


def _scene(n=40, degree=2, lang=6, seed=0, dtype=torch.float64):
    g = torch.Generator().manual_seed(seed)
    k = (degree + 1) ** 2 - 1
    r = lambda *s: torch.randn(*s, generator=g, dtype=dtype)  # noqa: E731
    return GaussianScene(r(n, 3) * 0.5, r(n, 3) * 0.3 - 2.3, r(n, 4), r(n) + 1, r(n, 3),
                         r(n, k, 3) * 0.2, r(n, lang) if lang else None)


def _camera(angle: float, w=24, h=18) -> Camera:
    """A camera 3 units from the origin, turned ``angle`` radians about the y axis, facing it."""
    c, s = torch.cos(torch.tensor(angle, dtype=torch.float64)), torch.sin(torch.tensor(angle, dtype=torch.float64))
    vm = torch.eye(4, dtype=torch.float64)
    vm[:3, :3] = torch.tensor([[c, 0.0, -s], [0.0, 1.0, 0.0], [s, 0.0, c]], dtype=torch.float64)
    vm[2, 3] = 3.0
    return Camera(vm, intrinsics(22.0, 22.0, w / 2, h / 2), w, h, image_name=f"cam{angle:.2f}")


KEYS = ("color", "alpha", "depth", "depth_accum", "radii", "means2d", "conics", "depths")


def test_render_with_a_colour_tensor_is_the_rasterizer():
    s = _scene(dtype=torch.float32)
    cam = _camera(0.3)
    cols = torch.rand(len(s), 5, generator=torch.Generator().manual_seed(1))
    bg = torch.tensor([0.1, 0.2, 0.3, 0.4, 0.5])
    out = s.render(cam, cols, background=bg, eps2d=0.2)
    ref = tiger.rasterize_gaussians(s.means, s.quats, torch.exp(s.log_scales),
                                    torch.sigmoid(s.opacity_logits), cols, cam.viewmat.float(),
                                    cam.K.float(), cam.width, cam.height, background=bg, eps2d=0.2)
    for k in KEYS:
        assert torch.equal(out[k], ref[k]), k
    assert out["n_isects"] == ref["n_isects"] > 0 and out["alpha"].max() > 0.3


def test_render_view_colors_are_the_sh_colour():
    s = _scene()
    cam = _camera(0.5)
    dirs = s.means - cam.center
    want = (sh_to_color_ref(dirs, s.sh, 1) + 0.5).clamp_min(0)
    torch.testing.assert_close(s.view_colors(cam, 1), want, rtol=1e-12, atol=1e-12)
    # the SH render and a render of those colours as plain channels are the same picture
    torch.testing.assert_close(s.render(cam, "rgb", sh_degree=1)["color"],
                               s.render(cam, s.view_colors(cam, 1))["color"], rtol=1e-12, atol=1e-12)
    both = s.render(cam, "rgb+lang", sh_degree=1)["color"]
    assert torch.equal(both[..., 3:], s.render(cam, torch.cat([s.view_colors(cam, 1), s.lang], 1))["color"][..., 3:])


def test_render_views_equals_per_camera_renders():
    s = _scene()
    cams = [_camera(a) for a in (0.0, 0.4, -0.7, 1.1)]
    for colors in (None, "lang", "rgb+lang", torch.rand(len(s), 3, dtype=torch.float64)):
        out = render_views(s, cams, colors, sh_degree=1)
        assert out["color"].shape[:3] == (4, 18, 24) and out["radii"].shape == (4, len(s))
        for v, cam in enumerate(cams):
            one = s.render(cam, colors, sh_degree=1)
            for k in KEYS:
                assert torch.equal(out[k][v], one[k]), (colors, k, v)
            assert int(out["n_isects"][v]) == one["n_isects"]


@pytest.mark.parametrize("device", DEVICES)
def test_render_view_chunks_group_consecutive_cameras_of_one_size(device):
    """Chunks of at most views_per_pass consecutive same-size cameras, in order, each view the
    single-camera render; render_rgb (which renders through them) refuses mixed sizes."""
    s = _scene().to(device=device)
    sizes = [(24, 18), (24, 18), (24, 18), (16, 12), (24, 18), (24, 18)]
    cams = [_camera(0.3 * i - 0.6, w, h) for i, (w, h) in enumerate(sizes)]
    chunks = list(render_view_chunks(s, cams, "rgb+lang", views_per_pass=2, sh_degree=1))
    assert [(first, out["color"].shape[0]) for first, out in chunks] == [(0, 2), (2, 1), (3, 1), (4, 2)]
    for first, out in chunks:
        for v in range(out["color"].shape[0]):
            one = s.render(cams[first + v], "rgb+lang", sh_degree=1)
            for k in KEYS:
                assert torch.equal(out[k][v], one[k]), (first, v, k)
    assert list(render_view_chunks(s, [])) == []
    with pytest.raises(ValueError, match="views_per_pass"):
        next(render_view_chunks(s, cams, views_per_pass=0))
    with pytest.raises(ValueError, match="one size"):
        render_rgb(s, cams)


def test_render_views_gradients_agree_with_per_camera_renders():
    cams = [_camera(a) for a in (0.0, 0.6, -0.9, 1.3)]
    weights = torch.rand(4, 18, 24, 3, generator=torch.Generator().manual_seed(2), dtype=torch.float64)

    def grads(batched: bool, colors_kind: str):
        s = _scene(seed=3)
        s.parameter_groups()
        cols = torch.rand(len(s), 3, dtype=torch.float64, generator=torch.Generator().manual_seed(4))
        cols.requires_grad_(True)
        colors = cols if colors_kind == "tensor" else None
        if batched:
            out = render_views(s, cams, colors)
            out["means2d"].retain_grad()
            loss = (out["color"] * weights).sum() + out["depth"].sum()
            loss.backward()
            m2d = out["means2d"].grad
        else:
            loss, parts = 0.0, []
            for v, cam in enumerate(cams):
                o = s.render(cam, colors)
                o["means2d"].retain_grad()
                parts.append(o["means2d"])
                loss = loss + (o["color"] * weights[v]).sum() + o["depth"].sum()
            loss.backward()
            m2d = torch.stack([p.grad for p in parts])
        g = {k: t.grad for k, t in s.params().items()}
        g["means2d"] = m2d
        if colors_kind == "tensor":
            g["colors"] = cols.grad
        return g

    for kind in ("sh", "tensor"):
        a, b = grads(True, kind), grads(False, kind)
        assert set(a) == set(b)
        for k in a:
            if a[k] is None:
                assert b[k] is None, k
                continue
            assert a[k].abs().max() > 0 or k == "lang", (kind, k)
            torch.testing.assert_close(a[k], b[k], rtol=1e-10, atol=1e-12, msg=f"{kind} {k}")


def test_render_views_checks_its_inputs():
    s = _scene()
    with pytest.raises(ValueError, match="camera 1 .* is 30x18"):
        render_views(s, [_camera(0.0), _camera(0.2, w=30)])
    with pytest.raises(ValueError, match="at least one camera"):
        render_views(s, [])
    with pytest.raises(ValueError, match=r"colors must be a per-Gaussian tensor \[N=40, C\], got \[39, 3\]"):
        s.render(_camera(0.0), torch.zeros(39, 3, dtype=torch.float64))
    with pytest.raises(ValueError, match="'depth'"):
        s.render(_camera(0.0), "depth")
    with pytest.raises(ValueError, match="no language features"):
        _scene(lang=0).render(_camera(0.0), "lang")


def test_render_rgb_is_the_clamped_sh_render_with_its_footprint_in_one_pass():
    """render_rgb (the one RGB-pictures helper) equals per-view GaussianScene.render of the SH colour,
    clamped, over more views than one pass holds; its footprint equals rendering the weights alone."""
    from tiger.scene import render_rgb
    from tiger.scene.gaussian_scene import RGB_VIEWS_PER_PASS

    s = _scene(dtype=torch.float32)
    cams = [_camera(0.2 * k) for k in range(RGB_VIEWS_PER_PASS + 3)]
    bg = torch.tensor([0.2, 0.5, 0.9])
    weights = (torch.arange(len(s)) % 3 == 0).float() * 0.75
    rgb, foot = render_rgb(s, cams, bg, footprint=weights)
    assert rgb.shape == (len(cams), 18, 24, 3) and foot.shape == (len(cams), 18, 24)
    for v, cam in enumerate(cams):
        want = s.render(cam, "rgb", background=bg)["color"].clamp(0, 1)
        assert torch.allclose(rgb[v], want, atol=1e-6), v
        alone = s.render(cam, weights[:, None])["color"][..., 0]
        assert torch.allclose(foot[v], alone.clamp(0, 1), atol=1e-6), v
    assert torch.equal(render_rgb(s, cams, bg), rgb)  # the footprint channel changes nothing
    assert 0.0 <= float(rgb.min()) and float(rgb.max()) <= 1.0 and float(foot.max()) > 0
    with pytest.raises(ValueError, match=r"footprint must be \[N=40\]"):
        render_rgb(s, cams, footprint=weights[:5])
    with pytest.raises(ValueError, match="background must be 3 numbers"):
        render_rgb(s, cams, (0.0, 1.0))
    with pytest.raises(ValueError, match="at least one camera"):
        render_rgb(s, [])


def _large_scene(dtype, device, n=50, seed=5):
    """_scene with a few Gaussians far larger than the image (they straddle every border of their
    view, and so the neighbouring views' bands of a batched render)."""
    s = _scene(n=n, seed=seed, dtype=dtype)
    s.log_scales[:4] += 2.5
    return s.to(device=device)


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
@pytest.mark.parametrize("views", [1, 2, 5])
def test_batched_render_views_are_the_single_camera_renders_with_gradients(device, dtype, views):
    """render_views of V cameras (37x29: partial tiles) equals V GaussianScene.render calls bit for
    bit (pixels, radii, means2d, conics, depths, per-view means2d gradients); the scene's
    gradients sum the views in another order: equal to float rounding."""
    cams = [_camera(0.35 * k - 0.5, w=37, h=29) for k in range(views)]
    g = torch.Generator().manual_seed(6)
    bg = torch.tensor([0.2, 0.4, 0.6], dtype=dtype, device=device)
    w_col = torch.rand(views, 29, 37, 3, generator=g, dtype=dtype).to(device)
    w_a = torch.rand(views, 29, 37, generator=g, dtype=dtype).to(device)

    def run(batched: bool):
        s = _large_scene(dtype, device)
        s.parameter_groups()
        if batched:
            out = render_views(s, cams, background=bg)
            out["means2d"].retain_grad()
            loss = (out["color"] * w_col).sum() + (out["alpha"] * w_a).sum() + 0.1 * out["depth"].sum()
            loss.backward()
            outs = [{k: out[k][v] for k in KEYS} for v in range(views)]
            m2d = out["means2d"].grad
            n_isects = out["n_isects"].tolist()
        else:
            outs, loss = [], 0.0
            for v, cam in enumerate(cams):
                o = s.render(cam, background=bg)
                o["means2d"].retain_grad()
                outs.append(o)
                loss = loss + (o["color"] * w_col[v]).sum() + (o["alpha"] * w_a[v]).sum() + 0.1 * o["depth"].sum()
            loss.backward()
            m2d = torch.stack([o["means2d"].grad for o in outs])
            n_isects = [o["n_isects"] for o in outs]
        return outs, m2d, n_isects, {k: t.grad for k, t in s.params().items()}

    b_outs, b_m2d, b_n, b_grads = run(True)
    o_outs, o_m2d, o_n, o_grads = run(False)
    assert b_n == o_n and min(b_n) > 0
    for v in range(views):
        for k in KEYS:
            assert torch.equal(b_outs[v][k], o_outs[v][k]), (k, v)
    assert float(b_outs[0]["alpha"].detach().amin()) > 0.05  # the large Gaussians cover every pixel
    tol = 1e-11 if dtype == torch.float64 else 2e-5
    if device == "cpu":
        assert torch.equal(b_m2d, o_m2d)
    else:  # the CUDA backward sums screen gradients with atomics: the order (and rounding) varies per run
        torch.testing.assert_close(b_m2d, o_m2d, rtol=tol, atol=tol)
    for k, a in b_grads.items():
        if a is None:
            assert o_grads[k] is None, k
            continue
        assert a.abs().max() > 0 or k == "lang", k
        torch.testing.assert_close(a, o_grads[k], rtol=tol, atol=tol, msg=k)


class _ShCalls(TorchDispatchMode):
    """Counts the SH ops dispatched (forward and backward)."""

    def __init__(self):
        super().__init__()
        self.calls = Counter()

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        if str(func).startswith("tiger.sh_to_color"):
            self.calls[str(func)] += 1
        return func(*args, **(kwargs or {}))


@pytest.mark.parametrize("colors", ["rgb", "rgb+lang"])
def test_render_views_evaluates_sh_once_for_all_views(colors):
    """render_views of 4 cameras: one SH forward and one SH backward (the views' coefficient
    gradients summed in the kernel), not one per view."""
    s = _scene(seed=8)
    s.parameter_groups()
    cams = [_camera(a) for a in (0.0, 0.5, -0.8, 1.2)]
    probe = _ShCalls()
    with probe:
        out = render_views(s, cams, colors)
        out["color"].sum().backward()
    assert dict(probe.calls) == {"tiger.sh_to_color.default": 1, "tiger.sh_to_color_backward.default": 1}
    assert s.sh_rest.grad.abs().max() > 0


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
@pytest.mark.parametrize("masked", [False, True])
def test_render_views_sh_matches_per_view_sh_calls(device, dtype, masked):
    """The batched SH step changes nothing: render_views' images equal, bit for bit, per-view renders
    of colours from one one-view SH call per view (the path before the V-view op, whose
    coefficient gradients autograd summed), and the scene's gradients agree to float rounding;
    with a trainable mask the frozen rows get none."""
    cams = [_camera(0.4 * k - 0.6, w=37, h=29) for k in range(4)]
    g = torch.Generator().manual_seed(9)
    bg = torch.tensor([0.1, 0.3, 0.5], dtype=dtype, device=device)
    w_col = torch.rand(4, 29, 37, 3, generator=g, dtype=dtype).to(device)
    trainable = (torch.arange(50) % 3 != 1).to(device) if masked else None

    def run(batched: bool):
        s = _large_scene(dtype, device)
        s.parameter_groups()
        if batched:
            color = render_views(s, cams, background=bg, trainable=trainable)["color"]
        else:
            views = []
            for cam in cams:
                c = cam.to(device=device, dtype=dtype)
                dirs = s.means - camera_center(c.viewmat)
                rgb = (sh_to_color(dirs, s.sh_dc[:, None], s.sh_degree, None, s.sh_rest) + 0.5).clamp_min(0)
                views.append(s.render(c, rgb, background=bg)["color"])
            color = torch.stack(views)
        (color * w_col).sum().backward()
        return color.detach(), {k: t.grad for k, t in s.params().items()}

    b_color, b_grads = run(True)
    o_color, o_grads = run(False)
    assert torch.equal(b_color, o_color)
    tol = 1e-11 if dtype == torch.float64 else 2e-5
    for k in ("means", "log_scales", "quats", "opacity_logits", "sh_dc", "sh_rest"):
        a, b = b_grads[k], o_grads[k]
        assert b.abs().max() > 0, k
        if trainable is not None:
            assert int(a[~trainable].count_nonzero()) == 0, k
            a, b = a[trainable], b[trainable]
        torch.testing.assert_close(a, b, rtol=tol, atol=tol, msg=k)
