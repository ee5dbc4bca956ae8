"""SceneOptimizer: any loss, a trainable mask (frozen rows bit-identical, no optimizer state),
relevance-scaled updates, per-group learning rates, exact resume."""
from __future__ import annotations

import io

import pytest
import torch

from .synthscene import ground_truth, render_views, sphere_cameras
from tiger.recon import SceneOptimizer, photometric_loss
from tiger.recon.strategy import DensifyStats, region_topk_densify
from tiger.scene.gaussian_scene import PARAM_NAMES

LRS = {"means": 1e-2, "log_scales": 5e-3, "quats": 1e-3, "opacity_logits": 5e-2, "sh_dc": 2.5e-3,
       "sh_rest": 1e-4}


def setup(n=40, seed=2):
    gt = ground_truth(24, seed=3).with_sh_degree(1)
    cams = sphere_cameras(6, size=20)
    start = ground_truth(n, seed=seed).with_sh_degree(1)
    start.lang = torch.randn(n, 5, generator=torch.Generator().manual_seed(seed))
    return start, cams, render_views(gt, cams)


def render(scene, batch):
    cam, _ = batch
    out = scene.render(cam, check_finite=False)
    out["means2d"].retain_grad()
    return out


def loss(out, batch):
    return photometric_loss(out["color"], batch[1], 0.2)


def run(opt, cams, imgs, steps, first=0):
    for i in range(first, first + steps):
        opt.step(loss, (cams[i % len(cams)], imgs[i % len(cams)]), render)


def row_numel(scene, names) -> int:
    return sum(getattr(scene, n)[0].numel() for n in names)


def test_frozen_rows_bit_identical_and_without_optimizer_state():
    scene, cams, imgs = setup()
    before = scene.clone()
    mask = torch.zeros(len(scene), dtype=torch.bool)
    mask[::3] = True
    opt = SceneOptimizer(scene, LRS, trainable=mask)
    run(opt, cams, imgs, 6)
    after = opt.scene
    for n in PARAM_NAMES:
        a, b = getattr(after, n), getattr(before, n)
        assert torch.equal(a[~mask], b[~mask]), n                       # frozen: bit-identical
        assert not a.requires_grad                                      # not a parameter
        if n in LRS:
            assert not torch.equal(a[mask], b[mask]), n                 # trainable rows moved
    assert torch.equal(after.lang, before.lang)                         # carried, not optimised
    # the optimizer holds [M] rows only
    M = int(mask.sum())
    for st in opt.optimizer.state.values():
        for k in ("exp_avg", "exp_avg_sq"):
            assert st[k].shape[0] == M
    assert opt.optimizer_state_bytes() == 2 * 4 * M * row_numel(after, LRS)


def test_optimizer_state_is_proportional_to_the_trainable_count():
    scene, cams, imgs = setup(n=60)
    sizes = {}
    for m in (6, 12, 30, 60):
        mask = torch.zeros(60, dtype=torch.bool)
        mask[torch.randperm(60, generator=torch.Generator().manual_seed(m))[:m]] = True
        opt = SceneOptimizer(scene.clone(), LRS, trainable=mask if m < 60 else None)
        run(opt, cams, imgs, 2)
        sizes[m] = opt.optimizer_state_bytes()
    per_row = {m: b / m for m, b in sizes.items()}
    assert len(set(per_row.values())) == 1, sizes
    assert per_row[6] == 2 * 4 * (3 + 3 + 4 + 1 + 3 + 9)                # fp32 exp_avg + exp_avg_sq


def test_masked_step_matches_full_adam_with_frozen_gradients_zeroed():
    """Independent reference: plain torch Adam over the whole tensors where the frozen rows'
    gradients are zeroed (zero moments -> zero update) gives the same trainable rows."""
    scene, cams, imgs = setup()
    mask = torch.rand(len(scene), generator=torch.Generator().manual_seed(5)) < 0.5
    ref = scene.clone()
    groups = ref.parameter_groups(LRS, names=list(LRS))
    adam = torch.optim.Adam(groups, lr=0.0, eps=1e-15)
    opt = SceneOptimizer(scene, LRS, trainable=mask)
    for i in range(4):
        batch = (cams[i], imgs[i])
        loss(render(ref, batch), batch).backward()
        for g in groups:
            g["params"][0].grad[~mask] = 0
        adam.step()
        adam.zero_grad()
        opt.step(loss, batch, render)
    for n in LRS:
        torch.testing.assert_close(getattr(opt.scene, n), getattr(ref, n).detach(), rtol=1e-6, atol=1e-7)


def test_update_weight_scales_the_adam_update_per_gaussian():
    scene, cams, imgs = setup()
    n = len(scene)
    w = torch.linspace(0, 1, n)
    plain = SceneOptimizer(scene.clone(), LRS)
    start = scene.clone()
    weighted = SceneOptimizer(scene, LRS, update_weight=w)
    batch = (cams[0], imgs[0])
    plain.step(loss, batch, render)
    weighted.step(loss, batch, render)
    for name in LRS:
        p0, p1 = getattr(start, name), getattr(plain.scene, name).detach()
        expect = p0 + w.view(-1, *([1] * (p0.dim() - 1))) * (p1 - p0)
        torch.testing.assert_close(getattr(weighted.scene, name).detach(), expect, rtol=1e-6, atol=1e-7)
        assert torch.equal(getattr(weighted.scene, name)[0], p0[0])       # weight 0: unchanged
    # moments are Adam's own (not scaled)
    for ga, gb in zip(plain.optimizer.param_groups, weighted.optimizer.param_groups):
        torch.testing.assert_close(plain.optimizer.state[ga["params"][0]]["exp_avg"],
                                   weighted.optimizer.state[gb["params"][0]]["exp_avg"])


def test_weighted_masked_steps_match_adam_on_the_rows_with_the_update_scaled():
    """Several relevance-scaled steps with a trainable mask (the edit's case: one scaled_adam_
    call writes the rows into the scene) against torch Adam on the trainable rows, each step's
    update scaled by hand and scattered back; the step counts and moments stay Adam's own."""
    scene, cams, imgs = setup()
    mask = torch.rand(len(scene), generator=torch.Generator().manual_seed(7)) < 0.6
    idx = torch.nonzero(mask).reshape(-1)
    w = torch.rand(len(scene), generator=torch.Generator().manual_seed(8))
    ref = scene.clone()
    rows = {n: getattr(ref, n)[idx].detach().clone().requires_grad_(True) for n in LRS}
    adam = torch.optim.Adam([{"params": [rows[n]], "lr": LRS[n]} for n in LRS], lr=0.0, eps=1e-15)
    opt = SceneOptimizer(scene, LRS, trainable=mask, update_weight=w)
    for i in range(4):
        batch = (cams[i], imgs[i])
        view = ref.clone()
        for n in LRS:
            setattr(view, n, getattr(ref, n).detach().index_put((idx,), rows[n]))
        loss(render(view, batch), batch).backward()
        olds = {n: r.detach().clone() for n, r in rows.items()}
        adam.step()
        adam.zero_grad()
        with torch.no_grad():
            for n, r in rows.items():
                r.copy_(torch.lerp(olds[n], r, w[idx].view(-1, *([1] * (r.dim() - 1)))))
                getattr(ref, n)[idx] = r
        opt.step(loss, batch, render)
    for n in LRS:
        torch.testing.assert_close(getattr(opt.scene, n), getattr(ref, n).detach(), rtol=1e-5, atol=1e-6)
        torch.testing.assert_close(opt.leaves[n].detach(), rows[n].detach(), rtol=1e-5, atol=1e-6)
        assert torch.equal(getattr(opt.scene, n)[~mask], getattr(ref, n)[~mask].detach())  # frozen rows untouched
    for g_ref, g in zip(adam.param_groups, opt.optimizer.param_groups):
        a, b = adam.state[g_ref["params"][0]], opt.optimizer.state[g["params"][0]]
        assert float(a["step"]) == float(b["step"]) == 4
        torch.testing.assert_close(b["exp_avg"], a["exp_avg"], rtol=1e-5, atol=1e-7)


def test_per_group_learning_rates_and_errors():
    scene, cams, imgs = setup()
    opt = SceneOptimizer(scene, {"sh_dc": 0.1, "means": 0.0})
    assert opt.names == ["means", "sh_dc"] and opt.lr("sh_dc") == 0.1
    opt.set_lr("means", 0.0)
    means = scene.means.detach().clone()
    run(opt, cams, imgs, 2)
    assert torch.equal(opt.scene.means.detach(), means)                  # lr 0: no move
    with pytest.raises(KeyError, match="not 'quats'"):
        opt.set_lr("quats", 1.0)
    with pytest.raises(ValueError, match="no per-Gaussian parameter"):
        SceneOptimizer(scene, {"colour": 1.0})
    with pytest.raises(ValueError, match=r"trainable must have one row per Gaussian \[N=40"):
        SceneOptimizer(scene, LRS, trainable=torch.ones(39, dtype=torch.bool))
    with pytest.raises(ValueError, match="bool mask"):
        SceneOptimizer(scene, LRS, trainable=torch.ones(40))
    with pytest.raises(ValueError, match="scalar"):
        opt.step(lambda out, b: out["color"], (cams[0], imgs[0]), render)


def test_state_dict_resume_equals_an_uninterrupted_run():
    scene, cams, imgs = setup()
    mask = torch.arange(len(scene)) % 2 == 0
    w = torch.rand(len(scene), generator=torch.Generator().manual_seed(1))
    extras = {"relevance": w.clone()}

    def make(s):
        return SceneOptimizer(s, LRS, trainable=mask, update_weight=w, extras=extras)

    def densify(opt, stats):
        region_topk_densify(opt, stats, extent=1.0, top_percent=20.0, generator=torch.Generator().manual_seed(0))

    def train(opt, stats, i0, i1):
        for i in range(i0, i1):
            res = opt.step(loss, (cams[i % 6], imgs[i % 6]), render)
            stats.add(res.renders["means2d"].grad, res.renders["radii"], 20, 20)
            if i == 2:
                densify(opt, stats)

    a = make(scene.clone())
    sa = DensifyStats.zeros(len(scene), torch.device("cpu"))
    train(a, sa, 0, 8)
    b = make(scene.clone())
    sb = DensifyStats.zeros(len(scene), torch.device("cpu"))
    train(b, sb, 0, 4)
    buf = io.BytesIO()
    torch.save({"opt": b.state_dict(), "stats": sb.state_dict()}, buf)
    buf.seek(0)
    saved = torch.load(buf, weights_only=True)
    c = make(setup(n=40, seed=9)[0])                                     # another scene, overwritten
    c.load_state_dict(saved["opt"])
    sc = DensifyStats.from_state_dict(saved["stats"])
    assert len(c.scene) > 40 and c.num_trainable == b.num_trainable
    train(c, sc, 4, 8)
    assert c.scene.equal(a.scene) and torch.equal(c.trainable, a.trainable)
    assert torch.equal(c.update_weight, a.update_weight) and torch.equal(c.extras["relevance"], a.extras["relevance"])


@pytest.mark.cuda
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_masked_step_on_cuda_matches_cpu():
    if not torch._C._dispatch_has_kernel_for_dispatch_key("tiger::rasterize", "CUDA"):
        pytest.skip("this build has no CUDA kernel for tiger::rasterize")
    scene, cams, imgs = setup()
    mask = torch.arange(len(scene)) % 3 == 0
    cpu = SceneOptimizer(scene.clone(), LRS, trainable=mask)
    gpu = SceneOptimizer(scene.clone().to("cuda"), LRS, trainable=mask.cuda())
    run(cpu, cams, imgs, 3)
    run(gpu, [c.to("cuda") for c in cams], [i.cuda() for i in imgs], 3)
    frozen = ~mask
    assert torch.equal(gpu.scene.means[frozen.cuda()].cpu(), scene.means[frozen])
    torch.testing.assert_close(gpu.scene.means.cpu(), cpu.scene.means, rtol=1e-4, atol=1e-5)


def test_adam_is_fused_on_cuda_only():
    start, _, _ = setup()
    assert SceneOptimizer(start, LRS).optimizer.defaults["fused"] is False   # CPU: torch's default Adam
    if torch.cuda.is_available() and torch._C._dispatch_has_kernel_for_dispatch_key("tiger::rasterize", "CUDA"):
        assert SceneOptimizer(start.to("cuda"), LRS).optimizer.defaults["fused"] is True
