"""INRIA's densification rule: clone small, split large, prune transparent/huge; optimizer rows follow."""
from __future__ import annotations

import math

import torch

from tiger.recon.step import SceneOptimizer
from tiger.recon.strategy import DensifyStats, inria_densify, reset_opacity
from tiger.scene import GaussianScene
from tiger.scene.gaussian_scene import inverse_sigmoid


def make():
    # 0: small, high gradient -> clone; 1: large, high gradient -> split;
    # 2: quiet -> kept as is; 3: transparent -> pruned; 4: huge in world -> pruned by size
    means = torch.tensor([[0.0, 0, 0], [1, 0, 0], [2, 0, 0], [3, 0, 0], [4, 0, 0]])
    scales = torch.tensor([0.005, 0.5, 0.005, 0.005, 5.0]).log()[:, None].repeat(1, 3)
    quats = torch.tensor([[1.0, 0, 0, 0]]).repeat(5, 1)
    op = inverse_sigmoid(torch.tensor([0.5, 0.6, 0.7, 0.001, 0.9]))
    sh_dc = torch.arange(15.0).reshape(5, 3)
    s = GaussianScene(means, scales, quats, op, sh_dc, torch.zeros(5, 3, 3))
    so = SceneOptimizer(s, {n: 1e-3 for n in s.params()})
    for p in s.params().values():
        p.grad = torch.ones_like(p)
    so.update()   # non-zero Adam moments for every Gaussian
    opt = so.optimizer
    stats = DensifyStats.zeros(5, torch.device("cpu"))
    # gradients in pixels of a 100x50 image: NDC norm = |(gx * 50, gy * 25)|
    g2d = torch.tensor([[1e-5, 0], [0, 2e-5], [1e-7, 0], [0, 0], [0, 0]])
    stats.add(g2d, torch.tensor([3, 3, 3, 3, 3]), 100, 50)
    return s, so, stats


def test_clone_split_prune():
    s, so, stats = make()
    opt = so.optimizer
    torch.testing.assert_close(stats.grad_accum, torch.tensor([5e-4, 5e-4, 5e-6, 0, 0]))
    old_dc = s.sh_dc.detach().clone()
    old_avg = opt.state[s.sh_dc]["exp_avg"].clone()
    big = s.scales[1].detach().clone()
    out = inria_densify(so, stats, grad_threshold=2e-4, extent=1.0, percent_dense=0.01,
                            min_opacity=0.005, max_world_size=1.0, generator=torch.Generator().manual_seed(0))
    assert out == {"cloned": 1, "split": 1, "pruned": 2, "total": 5, "before": 5}
    # order: kept originals (0, 2), then the clone of 0, then the two halves of 1
    torch.testing.assert_close(s.sh_dc.detach(), old_dc[[0, 2, 0, 1, 1]])
    assert torch.equal(s.means[2], s.means[0])
    halves = s.scales[3:].detach()
    torch.testing.assert_close(halves, (big / 1.6).expand(2, 3))
    assert (s.means[3:] - torch.tensor([1.0, 0, 0])).abs().max() < 4 * 0.5   # samples of the big Gaussian
    assert not torch.equal(s.means[3], s.means[4])
    avg = opt.state[s.sh_dc]["exp_avg"]
    torch.testing.assert_close(avg[:2], old_avg[[0, 2]])
    assert (avg[2:] == 0).all()
    for g in opt.param_groups:   # every group holds the scene's current tensor
        assert g["params"][0] is getattr(s, g["name"])
        assert opt.state[g["params"][0]]["exp_avg"].shape == g["params"][0].shape
    assert stats.grad_accum.shape == (5,) and (stats.count == 0).all()


def test_max_gaussians_caps_growth():
    s, opt, stats = make()
    inria_densify(opt, stats, 2e-4, 1.0, min_opacity=0.0, max_gaussians=5)
    assert len(s) == 5     # 5 existing, room for 0 more: nothing densified, nothing pruned
    s, opt, stats = make()
    out = inria_densify(opt, stats, 2e-4, 1.0, min_opacity=0.0, max_gaussians=6)
    assert out["cloned"] + out["split"] == 1


def test_reset_opacity_clamps_and_clears_moments():
    s, so, _ = make()
    opt = so.optimizer
    before = s.opacities.detach().clone()
    reset_opacity(so, 0.01)
    expected = torch.minimum(before, torch.tensor(0.01))
    torch.testing.assert_close(s.opacities.detach(), expected, rtol=1e-5, atol=1e-7)
    st = opt.state[s.opacity_logits]
    assert (st["exp_avg"] == 0).all() and (st["exp_avg_sq"] == 0).all()
    assert math.isclose(float(s.opacities[3].detach()), float(before[3]), rel_tol=1e-4) and before[3] < 0.01


def test_stats_add_views_known_answer():
    """[V, N] views at once equal the hand-computed sums; unseen (radius 0) views change nothing."""
    stats = DensifyStats.zeros(3, torch.device("cpu"))
    stats.max_radii[2] = 7.0  # an earlier window's value survives a view that does not see it
    g = torch.tensor([[[3e-3, 0.0], [0.0, 1e-3], [5.0, 5.0]],     # 10x20 image: NDC = (gx*5, gy*10)
                      [[0.0, 4e-3], [6e-3, 8e-3], [1.0, 1.0]]])
    radii = torch.tensor([[2, 4, 0], [5, 1, 0]], dtype=torch.int32)
    stats.add(g, radii, 10, 20)
    torch.testing.assert_close(stats.grad_accum, torch.tensor([0.015 + 0.04, 0.01 + (0.03**2 + 0.08**2) ** 0.5, 0.0]))
    torch.testing.assert_close(stats.count, torch.tensor([2.0, 2.0, 0.0]))
    torch.testing.assert_close(stats.max_radii, torch.tensor([5.0, 4.0, 7.0]))
    one = DensifyStats.zeros(3, torch.device("cpu"))
    one.max_radii[2] = 7.0
    for v in range(2):  # one view at a time: the same statistics
        one.add(g[v], radii[v], 10, 20)
    for a, b in zip(one.state_dict().values(), stats.state_dict().values()):
        torch.testing.assert_close(a, b)
