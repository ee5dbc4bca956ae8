"""GaussianScene: construction, subsets, concatenation, optimizer groups, rendering, checkpoints."""
from __future__ import annotations

import math

import pytest
import torch

import tiger
from tiger.render import Camera
from tiger.scene import GaussianScene, SceneFormatError
from tiger.scene.cameras import intrinsics
from tiger.scene.checkpoint import load_checkpoint, save_checkpoint
from tiger.scene.gaussian_scene import knn_mean_distance


def scene(n=30, degree=2, lang=0, seed=0):
    g = torch.Generator().manual_seed(seed)
    k = (degree + 1) ** 2 - 1
    r = lambda *s: torch.randn(*s, generator=g)  # noqa: E731
    return GaussianScene(r(n, 3) * 0.5, r(n, 3) * 0.3 - 2.5, r(n, 4), r(n) + 1, r(n, 3), r(n, k, 3) * 0.2,
                         r(n, lang) if lang else None)


def front_camera(w=40, h=30):
    vm = torch.eye(4, dtype=torch.float64)
    vm[2, 3] = 3.0   # the origin is 3 units in front of the camera
    return Camera(vm, intrinsics(40.0, 40.0, w / 2, h / 2), w, h, image_name="front")


def test_validation_names_the_tensor():
    s = scene()
    with pytest.raises(ValueError, match="quats must be"):
        GaussianScene(s.means, s.log_scales, s.quats[:, :3], s.opacity_logits, s.sh_dc)
    with pytest.raises(ValueError, match="sh_rest"):
        GaussianScene(s.means, s.log_scales, s.quats, s.opacity_logits, s.sh_dc, torch.zeros(30, 5, 3))
    with pytest.raises(ValueError, match="opacity_logits is torch.float64"):
        GaussianScene(s.means, s.log_scales, s.quats, s.opacity_logits.double(), s.sh_dc)


def test_subset_concat_and_sh_padding():
    a, b = scene(10, 2, lang=8, seed=1), scene(7, 1, lang=8, seed=2)
    c = GaussianScene.concat([a, b])
    assert len(c) == 17 and c.sh_degree == 2
    assert torch.equal(c.sh_rest[10:, :3], b.sh_rest) and (c.sh_rest[10:, 3:] == 0).all()
    assert torch.equal(c.subset(torch.arange(10)).means, a.means)
    mask = torch.zeros(17, dtype=torch.bool)
    mask[[1, 12]] = True
    s = c.subset(mask)
    assert torch.equal(s.lang, torch.stack([a.lang[1], b.lang[2]]))
    with pytest.raises(ValueError, match="language"):
        GaussianScene.concat([a, scene(3, 2)])
    with pytest.raises(ValueError, match="subset mask"):
        c.subset(torch.ones(3, dtype=torch.bool))
    assert c.with_sh_degree(0).sh_rest.shape == (17, 0, 3)
    assert torch.equal(c.with_sh_degree(3).sh_rest[:, :8], c.sh_rest)


def test_to_clone_and_parameter_groups():
    s = scene(lang=4)
    d = s.to(dtype=torch.float64)
    assert d.dtype == torch.float64 and d.lang.dtype == torch.float64 and s.dtype == torch.float32
    groups = s.parameter_groups({"means": 0.5}, names=["means", "sh_dc", "lang"])
    assert [g["name"] for g in groups] == ["means", "sh_dc", "lang"]
    assert groups[0]["lr"] == 0.5 and groups[0]["params"][0] is s.means
    assert s.means.requires_grad and not s.quats.requires_grad
    c = s.clone()
    assert not c.means.requires_grad and c.equal(s)
    with pytest.raises(ValueError, match="no parameter named 'colour'"):
        s.parameter_groups(names=["colour"])


def test_from_points_matches_inria_initialisation():
    pts = torch.tensor([[0.0, 0, 0], [1, 0, 0], [0, 2, 0], [0, 0, 3], [5, 5, 5]])
    s = GaussianScene.from_points(pts, torch.full((5, 3), 0.75), sh_degree=3)
    # scale = sqrt(mean of the squared distances to the 3 nearest neighbours)
    d = torch.cdist(pts.double(), pts.double()) + torch.eye(5, dtype=torch.float64) * 1e9
    ref = d.square().sort(1).values[:, :3].mean(1).sqrt()
    torch.testing.assert_close(s.scales[:, 0].double(), ref, rtol=1e-6, atol=0)
    torch.testing.assert_close(knn_mean_distance(pts).double(), ref, rtol=1e-6, atol=0)
    torch.testing.assert_close(s.opacities, torch.full((5,), 0.1))
    torch.testing.assert_close(s.rgb, torch.full((5, 3), 0.75))
    assert s.sh_degree == 3 and (s.sh_rest == 0).all() and (s.quats[:, 0] == 1).all()


def test_render_is_the_rasterizer_on_the_scene_tensors():
    s = scene(40, 2, lang=5)
    cam = front_camera()
    out = s.render(cam, sh_degree=1)
    ref = tiger.rasterize_gaussians(s.means, s.quats, torch.exp(s.log_scales), torch.sigmoid(s.opacity_logits),
                                    s.sh[:, :4], cam.viewmat.float(), cam.K.float(), 40, 30, sh_degree=1)
    assert torch.equal(out["color"], ref["color"]) and out["alpha"].max() > 0.1
    lang = s.render(cam, "lang")["color"]
    both = s.render(cam, "rgb+lang")["color"]
    torch.testing.assert_close(both[..., 3:], lang, atol=1e-6, rtol=1e-5)
    torch.testing.assert_close(both[..., :3], s.render(cam)["color"], atol=1e-6, rtol=1e-5)
    with pytest.raises(ValueError, match="sh_degree must be in 0..2"):
        s.render(cam, sh_degree=3)


def test_checkpoint_round_trip_with_optimizer(tmp_path):
    s = scene(lang=3)
    s.metadata = {"name": "ck"}
    opt = torch.optim.Adam(s.parameter_groups(), eps=1e-15)
    cam = front_camera()
    for _ in range(3):
        s.render(cam)["color"].sum().backward()
        opt.step()
        opt.zero_grad()
    p = tmp_path / "ck.pt"
    save_checkpoint(p, s, opt, step=3, extra={"note": [1, 2]})
    assert [f.name for f in tmp_path.iterdir()] == ["ck.pt"]     # no temp file left behind
    ck = load_checkpoint(p)
    assert ck["step"] == 3 and ck["extra"] == {"note": [1, 2]} and ck["scene"].equal(s.detach())
    t = ck["scene"]
    opt2 = torch.optim.Adam(t.parameter_groups(), eps=1e-15)
    opt2.load_state_dict(ck["optimizer"])
    for o in (opt, opt2):
        o.param_groups[0]["params"][0].grad = torch.ones_like(o.param_groups[0]["params"][0])
        o.step()
    assert torch.equal(s.means, t.means)   # identical Adam moments -> identical next step
    p.write_bytes(p.read_bytes()[:100])
    with pytest.raises(SceneFormatError, match="ck.pt.*cannot read checkpoint"):
        load_checkpoint(p)
    torch.save({"weights": torch.zeros(2)}, p)
    with pytest.raises(SceneFormatError, match="not a TIGER checkpoint"):
        load_checkpoint(p)


def test_scene_extent_is_inria_radius():
    from tiger.scene import scene_extent

    cams = []
    for x in (-1.0, 3.0):
        vm = torch.eye(4, dtype=torch.float64)
        vm[0, 3] = -x     # centre at (x, 0, 0)
        cams.append(Camera(vm, intrinsics(1, 1, 1, 1), 2, 2))
    assert scene_extent(cams) == pytest.approx(2.0 * 1.1)
    assert math.isfinite(scene_extent(cams[:1]))


def test_render_without_gradients_is_one_op_with_the_same_values(monkeypatch):
    """GaussianScene.render under no_grad goes through tiger::render_forward (what the viewer,
    `tiger render` and evaluation run) and gives the op-by-op render's values, every colour input."""
    from tiger.render import rasterize as raster_mod

    s = scene(60, 2, lang=5)
    s.parameter_groups()  # its tensors require grad: a render records gradients unless no_grad
    cam = front_camera()
    calls = []
    real = raster_mod.render_forward
    monkeypatch.setattr(raster_mod, "render_forward", lambda *a, **k: calls.append(1) or real(*a, **k))
    tint = torch.rand(60, 4, generator=torch.Generator().manual_seed(1))
    for colors in (None, "lang", "rgb+lang", tint, ("rgb", tint)):
        want = s.render(cam, colors, sh_degree=1)  # recorded: op by op
        assert want["color"].requires_grad
        with torch.no_grad():
            got = s.render(cam, colors, sh_degree=1)
        for k in ("color", "alpha", "depth", "radii", "means2d"):
            assert torch.equal(got[k], want[k].detach()), (colors if isinstance(colors, str) else "tensor", k)
    assert len(calls) == 5
