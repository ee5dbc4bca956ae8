"""The reconstruction trainer: refit a known scene, resume exactly, fine-tune, init, errors."""
from __future__ import annotations

import pytest
import torch

from .synthscene import ground_truth, render_views, sphere_cameras
from tiger.recon import ReconConfig, Trainer, psnr
from tiger.scene import GaussianScene
from tiger.scene.checkpoint import load_checkpoint

SYNTH = dict(iterations=900, sh_degree=0, lr_means_init=8e-4, lr_means_final=8e-6, densify_from=100,
             densify_until=540, densify_interval=50, opacity_reset_interval=0, max_gaussians=1000,
             init_random_points=300, progress=False)


def synthetic_fit(device: str = "cpu") -> tuple:
    gt = ground_truth(64)
    train, test = sphere_cameras(24), sphere_cameras(8, offset=0.5)   # disjoint held-out views
    tr = Trainer(train, render_views(gt, train), ReconConfig(**SYNTH), device=device,
                 test_cameras=test, test_images=render_views(gt, test))
    tr.fit()
    return tr, tr.evaluate()


@pytest.mark.timeout(600)
def test_synthetic_scene_refit_from_random_init_reaches_30db():
    tr, m = synthetic_fit()
    assert m["psnr"] >= 30.0, m
    assert m["ssim"] > 0.95
    assert min(p for p, _ in m["per_view"]) > 27.0          # no view is left behind
    assert 64 <= len(tr.scene) <= SYNTH["max_gaussians"]


@pytest.mark.cuda
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_synthetic_refit_on_cuda():
    if not torch._C._dispatch_has_kernel_for_dispatch_key("tiger::rasterize", "CUDA"):
        pytest.skip("this build has no CUDA kernel for tiger::rasterize")
    tr, m = synthetic_fit("cuda")
    assert tr.scene.device.type == "cuda" and m["psnr"] >= 30.0, m


def small_setup(n_views=10, size=24):
    gt = ground_truth(20, seed=3)
    cams = sphere_cameras(n_views, size=size)
    return gt, cams, render_views(gt, cams)


def small_config(**kw):
    base = dict(iterations=40, sh_degree=1, sh_increase_every=15, densify_from=5, densify_until=35,
                densify_interval=10, opacity_reset_interval=20, init_random_points=60, progress=False,
                random_background=True, lr_means_init=1e-3)
    base.update(kw)
    return ReconConfig(**base)


def test_resume_from_checkpoint_continues_identically(tmp_path):
    gt, cams, imgs = small_setup()
    a = Trainer(cams, imgs, small_config())
    a.fit()

    b = Trainer(cams, imgs, small_config(), out_dir=tmp_path)
    for _ in range(20):   # stop half way, right after an opacity reset and a densification
        b.train_step()
    b.save(tmp_path / "half.pt")
    c = Trainer(cams, imgs, small_config())
    c.load(tmp_path / "half.pt")
    assert c.step == 20 and len(c.scene) == len(b.scene)
    c.fit()
    assert c.step == a.step == 40
    assert c.scene.detach().equal(a.scene.detach())
    # fit() with out_dir leaves a final checkpoint that reloads to the same scene
    b.fit()
    ck = load_checkpoint(tmp_path / "checkpoint.pt")
    assert ck["step"] == 40 and ck["scene"].equal(b.scene.detach())


def test_finetune_starts_from_scene_and_improves_it():
    gt, cams, imgs = small_setup(size=32)
    gt = gt.with_sh_degree(2)
    start = gt.clone()
    start.sh_dc = start.sh_dc + 0.6                      # a wrong colour everywhere
    start.means = start.means + 0.03 * torch.randn(start.means.shape, generator=torch.Generator().manual_seed(0))
    cfg = ReconConfig.finetune(150, sh_degree=2, progress=False, densify=False)
    tr = Trainer(cams, imgs, cfg, scene=start)
    assert tr.active_sh == 2 and len(tr.scene) == len(start)
    before = tr.evaluate(cams, imgs)["psnr"]
    tr.fit()
    after = tr.evaluate(cams, imgs)["psnr"]
    assert after > max(before + 5.0, 28.0), (before, after)
    assert len(tr.scene) == len(start)                   # densify=False keeps the Gaussians


def test_initialisation_from_points_and_bounds():
    gt, cams, imgs = small_setup()
    pts = torch.randn(50, 3) * 0.3
    cols = torch.rand(50, 3)
    tr = Trainer(cams, imgs, ReconConfig(iterations=0, progress=False), init_points=pts, init_colors=cols)
    s = tr.fit()
    assert torch.equal(s.means, pts) and torch.allclose(s.rgb, cols, atol=1e-6)
    tr = Trainer(cams, imgs, ReconConfig(iterations=0, progress=False, init_random_points=400,
                                         init_min_view_fraction=1.0))
    # every random point is seen by every camera
    for c in cams:
        uv, z = c.project(tr.scene.means.double())
        assert (z > 0).all() and (uv >= 0).all() and (uv[:, 0] < c.width).all() and (uv[:, 1] < c.height).all()


def test_trainer_input_errors():
    gt, cams, imgs = small_setup()
    with pytest.raises(ValueError, match="image 3 .* is 24x23 but its camera is 24x24"):
        Trainer(cams, imgs[:3] + [imgs[3][:23]] + imgs[4:], ReconConfig(progress=False))
    with pytest.raises(ValueError, match="10 cameras but 9 images"):
        Trainer(cams, imgs[:9])
    from tiger.render import Distortion

    cams[0].distortion = Distortion(k1=0.1)
    with pytest.raises(ValueError, match="lens distortion"):
        Trainer(cams, imgs)


def test_psnr_of_evaluate_matches_direct_render():
    gt, cams, imgs = small_setup()
    tr = Trainer(cams, imgs, ReconConfig(iterations=0, progress=False), scene=gt.with_sh_degree(3))
    m = tr.evaluate(cams, imgs)
    direct = [psnr(gt.render(c)["color"].clamp(0, 1), im) for c, im in zip(cams, imgs)]
    assert m["psnr"] == pytest.approx(sum(direct) / len(direct), rel=1e-5)
    assert isinstance(tr.scene, GaussianScene)


def test_pixels_outside_the_mask_do_not_train_and_do_not_count():
    """With L1 only, garbage outside the masks gives bit-identically the same fit as clean
    targets; PSNR over a mask equals PSNR of the selected pixels."""
    gt, cams, imgs = small_setup()
    masks = [torch.ones(24, 24, dtype=torch.bool) for _ in cams]
    for m in masks:
        m[:, :4] = False                                            # a black border, as undistortion leaves
    g = torch.Generator().manual_seed(0)
    garbage = [torch.where(m[..., None], im, torch.rand(im.shape, generator=g)) for im, m in zip(imgs, masks)]
    cfg = small_config(iterations=25, lambda_dssim=0.0)
    a = Trainer(cams, imgs, cfg, masks=masks)
    a.fit()
    b = Trainer(cams, garbage, cfg, masks=masks, test_cameras=cams, test_images=garbage, test_masks=masks)
    b.fit()
    assert a.scene.detach().equal(b.scene.detach())
    assert b.evaluate()["psnr"] == pytest.approx(a.evaluate(cams, imgs, masks)["psnr"], rel=1e-6)
    out = a.scene.render(cams[0])["color"].detach()
    by_hand = -10 * torch.log10(((out.clamp(0, 1) - imgs[0]) ** 2)[:, 4:].mean())
    assert psnr(out, imgs[0], masks[0]) == pytest.approx(float(by_hand), rel=1e-5)
    with pytest.raises(ValueError, match=r"masks\[2\] must be \[H, W\] = \[24, 24\] bool"):
        Trainer(cams, imgs, cfg, masks=masks[:2] + [masks[2][:, :5]] + masks[3:])


def test_appearance_fits_per_image_colour_and_resumes_exactly(tmp_path):
    from tiger.recon.appearance import AffineAppearance, fit_affine_colour

    # the least-squares diagnostic recovers a known affine map exactly
    r = torch.rand(20, 30, 3, dtype=torch.float64)
    A = torch.tensor([[0.9, 0.05, 0.0], [0.0, 1.1, 0.02], [0.03, 0.0, 0.8]], dtype=torch.float64)
    t = r @ A.T + torch.tensor([0.02, -0.01, 0.05], dtype=torch.float64)
    torch.testing.assert_close(fit_affine_colour(r, t), t, rtol=0, atol=1e-12)
    app = AffineAppearance(3)
    assert torch.equal(app(r.float(), 2), r.float())                      # identity at the start
    # training images with a per-view exposure: the corrections move, resume is exact
    gt, cams, imgs = small_setup()
    gains = torch.linspace(0.8, 1.2, len(imgs))
    imgs = [(im * k).clamp(0, 1) for im, k in zip(imgs, gains)]
    cfg = small_config(appearance=True, lr_appearance=1e-2)
    a = Trainer(cams, imgs, cfg)
    a.fit()
    assert not torch.equal(a.appearance.matrix, torch.eye(3).repeat(len(cams), 1, 1))
    b = Trainer(cams, imgs, cfg)
    for _ in range(20):
        b.train_step()
    b.save(tmp_path / "half.pt")
    c = Trainer(cams, imgs, cfg)
    c.load(tmp_path / "half.pt")
    c.fit()
    assert c.scene.detach().equal(a.scene.detach())
    assert torch.equal(c.appearance.matrix, a.appearance.matrix) and torch.equal(c.appearance.bias, a.appearance.bias)


def test_finetune_a_region_leaves_the_rest_bit_identical_and_resumes(tmp_path):
    gt, cams, imgs = small_setup()
    start = gt.with_sh_degree(1)
    start.sh_dc = start.sh_dc + 0.3
    region = torch.arange(len(start)) < 8
    cfg = small_config(iterations=30, densify_from=2, densify_interval=5, densify_grad_threshold=1e-9,
                       opacity_reset_interval=0, random_background=False)
    a = Trainer(cams, imgs, cfg, scene=start, trainable=region)
    a.fit()
    n_region = int(a.opt.trainable.sum())
    assert len(a.scene) > len(start) and n_region > 8                   # the region densified
    frozen = ~a.opt.trainable
    assert int(frozen.sum()) == 12
    for name, t in start.params().items():
        assert torch.equal(getattr(a.scene, name)[frozen], t[~region]), name
    assert a.opt.optimizer_state_bytes() == 2 * 4 * n_region * (3 + 3 + 4 + 1 + 3 + 9)
    b = Trainer(cams, imgs, cfg, scene=start, trainable=region)
    for _ in range(13):
        b.train_step()
    b.save(tmp_path / "half.pt")
    c = Trainer(cams, imgs, cfg, scene=start, trainable=region)
    c.load(tmp_path / "half.pt")
    c.fit()
    assert c.scene.detach().equal(a.scene.detach())
    with pytest.raises(ValueError, match="needs a starting scene"):
        Trainer(cams, imgs, cfg, trainable=region)


def test_step_metrics_without_read_back_equal_the_read_back_ones():
    """train_step(read_back=False) returns the same loss and PSNR as 0-d tensors (no host sync);
    the two trainers take identical steps either way."""
    _, cams, imgs = small_setup()
    a, b = Trainer(cams, imgs, small_config()), Trainer(cams, imgs, small_config())
    for _ in range(12):   # across a densification step
        ia, ib = a.train_step(), b.train_step(read_back=False)
        assert isinstance(ib["loss"], torch.Tensor) and ib["loss"].dim() == 0
        assert isinstance(ib["psnr"], torch.Tensor) and ib["psnr"].dim() == 0
        assert ia["loss"] == float(ib["loss"]) and ia["psnr"] == float(ib["psnr"])
        assert ia["gaussians"] == ib["gaussians"]
    assert torch.equal(a.scene.means, b.scene.means)
