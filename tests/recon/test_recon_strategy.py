"""Densification primitives keep Adam's moments aligned with the Gaussians (checked by an
independent Adam recomputation), children inherit every attribute (``lang`` included), and
the region rules stay inside their region and budget."""
from __future__ import annotations

import math

import pytest
import torch

from tiger.recon import SceneOptimizer
from tiger.recon.strategy import (DensifyStats, clone_and_split, duplicate, prune_transparent, region_topk_densify, remove,
                                  reset_opacity, split)
from tiger.scene import GaussianScene
from tiger.scene.gaussian_scene import inverse_sigmoid

LR = 0.01
BETAS = (0.9, 0.999)
EPS = 1e-8


def make_scene(n=12, seed=0) -> GaussianScene:
    g = torch.Generator().manual_seed(seed)
    s = GaussianScene(torch.randn(n, 3, generator=g), torch.log(0.01 + 0.5 * torch.rand(n, 3, generator=g)),
                      torch.randn(n, 4, generator=g), torch.randn(n, generator=g), torch.randn(n, 3, generator=g),
                      torch.randn(n, 3, 3, generator=g), lang=torch.randn(n, 4, generator=g))
    return s


def warm(trainable=None, n=12, seed=0):
    """An optimizer whose trainable rows hold distinct non-zero Adam moments; extras["id"]
    tracks which original row each Gaussian descends from."""
    s = make_scene(n, seed)
    lrs = {k: LR for k in ("means", "log_scales", "quats", "opacity_logits", "sh_dc", "sh_rest")}
    opt = SceneOptimizer(s, lrs, trainable=trainable, betas=BETAS, eps=EPS,
                         extras={"id": torch.arange(n), "relevance": torch.rand(n)})
    g = torch.Generator().manual_seed(seed + 1)
    for _ in range(2):
        for leaf in opt._leaves.values():
            leaf.grad = torch.randn(leaf.shape, generator=g)
        opt.update()
    return opt


def moments(opt) -> dict:
    """name -> (exp_avg, exp_avg_sq, step) of the trainable rows, as [M, ...] copies."""
    out = {}
    for gr in opt.optimizer.param_groups:
        st = opt.optimizer.state[gr["params"][0]]
        out[gr["name"]] = (st["exp_avg"].clone(), st["exp_avg_sq"].clone(), float(st["step"]))
    return out


def adam_reference(p, g, m, v, step):
    """One Adam step written out from Kingma & Ba (bias-corrected), in float64."""
    p, g, m, v = (t.double() for t in (p, g, m, v))
    m = BETAS[0] * m + (1 - BETAS[0]) * g
    v = BETAS[1] * v + (1 - BETAS[1]) * g * g
    t = step + 1
    mhat, vhat = m / (1 - BETAS[0] ** t), v / (1 - BETAS[1] ** t)
    return p - LR * mhat / (vhat.sqrt() + EPS)


def check_aligned(opt, before_m, before_rows, child_start):
    """Rows [:child_start] descend from the original row extras['id']; rows after are children
    (zero moments). Then one more Adam step must equal the reference recomputed from the
    original rows' moments."""
    ids = opt.extras["id"]
    tr = opt.trainable_mask()
    pos_before = torch.cumsum(before_rows, 0) - 1                     # original row -> its [M] position
    after_m = moments(opt)
    g = torch.Generator().manual_seed(7)
    grads = {n: torch.randn(leaf.shape, generator=g) for n, leaf in opt._leaves.items()}
    params_before = {n: leaf.detach().clone() for n, leaf in opt._leaves.items()}
    rows = torch.nonzero(tr).reshape(-1)
    for n, leaf in opt._leaves.items():
        leaf.grad = grads[n].clone()
    opt.update()
    for n, (m_old, v_old, step) in before_m.items():
        m_new, v_new, _ = after_m[n]
        for j, r in enumerate(rows.tolist()):
            if r < child_start:
                src = pos_before[ids[r]]
                assert torch.equal(m_new[j], m_old[src]) and torch.equal(v_new[j], v_old[src]), (n, r)
                m0, v0 = m_old[src], v_old[src]
            else:
                assert (m_new[j] == 0).all() and (v_new[j] == 0).all(), (n, r)
                m0, v0 = torch.zeros_like(m_new[j]), torch.zeros_like(v_new[j])
            expect = adam_reference(params_before[n][j], grads[n][j], m0, v0, step)
            torch.testing.assert_close(opt._leaves[n][j].detach().double(), expect, rtol=1e-5, atol=1e-6)


@pytest.mark.parametrize("masked", [False, True])
def test_primitives_keep_adam_moments_aligned(masked):
    n = 12
    trainable = (torch.arange(n) % 3 != 0) if masked else None
    for op in ("duplicate", "split", "remove"):
        opt = warm(trainable, n)
        before = moments(opt)
        rows_before = opt.trainable_mask().clone()
        mask = torch.zeros(n, dtype=torch.bool)
        mask[[1, 2, 3, 7, 11]] = True
        if op == "duplicate":
            assert duplicate(opt, mask) == 5
            assert len(opt.scene) == n + 5
            start = n
        elif op == "split":
            assert split(opt, mask, generator=torch.Generator().manual_seed(0)) == 5
            assert len(opt.scene) == n + 5
            start = n - 5
        else:
            assert remove(opt, mask) == 5
            assert len(opt.scene) == n - 5
            start = n - 5
            assert not bool(torch.isin(opt.extras["id"], torch.tensor([1, 2, 3, 7, 11])).any())
        assert opt.optimizer_state_bytes() == opt.num_trainable * 2 * 4 * (3 + 3 + 4 + 1 + 3 + 9)
        if masked:  # children of frozen parents are frozen, of trainable ones trainable
            assert torch.equal(opt.trainable_mask(), rows_before[opt.extras["id"]])
        check_aligned(opt, before, rows_before, start)


def test_children_inherit_every_attribute_including_lang():
    opt = warm(trainable=torch.arange(12) >= 4)
    s0 = opt.scene.clone()
    rel0 = opt.extras["relevance"].clone()
    mask = torch.zeros(12, dtype=torch.bool)
    mask[[0, 5, 9]] = True
    duplicate(opt, mask)
    split(opt, torch.cat([mask, torch.zeros(3, dtype=torch.bool)]), generator=torch.Generator().manual_seed(1))
    s, ids = opt.scene, opt.extras["id"]
    assert len(s) == 12 + 3 + 3
    assert torch.equal(s.lang, s0.lang[ids])                                  # language embedding
    assert torch.equal(opt.extras["relevance"], rel0[ids])
    for name in ("quats", "opacity_logits", "sh_dc", "sh_rest"):
        assert torch.equal(getattr(s, name), getattr(s0, name)[ids]), name
    split_children = slice(len(s) - 6, None)                                  # 2 per split parent
    torch.testing.assert_close(s.scales[split_children], s0.scales[ids[split_children]] / 1.6)
    assert torch.equal(s.means[:12], s0.means[ids[:12]])                     # originals and clones


def test_reset_opacity_in_a_mask_only():
    opt = warm()
    s = opt.scene
    op0 = s.opacities.detach().clone()
    logit0 = s.opacity_logits.detach().clone()
    mask = torch.arange(12) < 6
    m_before = moments(opt)["opacity_logits"][0]
    reset_opacity(opt, 0.01, mask)
    torch.testing.assert_close(s.opacities.detach()[mask], torch.minimum(op0[mask], torch.tensor(0.01)),
                               rtol=1e-5, atol=1e-7)
    assert torch.equal(s.opacity_logits.detach()[~mask], logit0[~mask])
    m_after = moments(opt)["opacity_logits"][0]
    assert (m_after[mask] == 0).all() and torch.equal(m_after[~mask], m_before[~mask])


def stats_with(grads: torch.Tensor) -> DensifyStats:
    st = DensifyStats.zeros(len(grads), torch.device("cpu"))
    st.grad_accum = grads.clone()
    st.count = (grads > 0).float()
    return st


def test_region_topk_adds_at_most_k_percent_inside_the_region():
    n = 1000
    s = make_scene(n, seed=3)
    region = torch.zeros(n, dtype=torch.bool)
    region[200:700] = True                                                   # 500 Gaussians
    opt = SceneOptimizer(s, {"means": 1e-3, "sh_dc": 1e-3}, trainable=region, extras={"id": torch.arange(n)})
    grads = torch.rand(n, generator=torch.Generator().manual_seed(4))
    grads[:200] += 10                                                         # strongest outside: ignored
    out = region_topk_densify(opt, stats_with(grads), extent=1.0, top_percent=1.0,
                              generator=torch.Generator().manual_seed(0))
    assert out["cloned"] + out["split"] == 5 and out["total"] - out["before"] == 5   # floor(1 % of 500)
    parents = opt.extras["id"][len(opt.scene) - 5 - out["split"]:]
    expect = torch.topk(torch.where(region, grads, torch.zeros(n)), 5).indices
    assert set(parents.tolist()) == set(expect.tolist())
    assert opt.trainable_mask()[n - out["split"]:].all()                     # children are trainable
    # repeated calls: each adds at most 1 % of the current region; zero gradients never densify
    for pct in (1.0, 5.0, 0.1):
        m = opt.num_trainable
        st = stats_with(torch.rand(len(opt.scene)) * opt.trainable_mask())
        o = region_topk_densify(opt, st, extent=1.0, top_percent=pct)
        assert o["total"] - o["before"] == math.floor(pct / 100 * m)
        assert (st.grad_accum == 0).all()                                    # a new window
    o = region_topk_densify(opt, stats_with(torch.zeros(len(opt.scene))), extent=1.0)
    assert o["total"] == o["before"]
    with pytest.raises(ValueError, match="top_percent"):
        region_topk_densify(opt, stats_with(torch.zeros(len(opt.scene))), extent=1.0, top_percent=150)


def test_prune_transparent_only_inside_the_region():
    s = make_scene(10)
    s.opacity_logits = inverse_sigmoid(torch.tensor([0.001, 0.5] * 5))
    region = torch.arange(10) < 6
    opt = SceneOptimizer(s, {"opacity_logits": 1e-3}, extras={"id": torch.arange(10)})
    assert prune_transparent(opt, 0.005, region) == 3
    assert opt.extras["id"].tolist() == [1, 3, 5, 6, 7, 8, 9]
    with pytest.raises(ValueError, match=r"remove mask must be \[N=7\] bool"):
        remove(opt, torch.ones(10, dtype=torch.bool))


def _snapshot(opt, state) -> dict:
    out = {f"param.{k}": v.detach().clone() for k, v in opt.scene.params().items() if v is not None}
    out.update({f"extra.{k}": v.clone() for k, v in opt.extras.items()})
    out.update({f"state.{k}": v.clone() for k, v in state.items()})
    out.update({f"moment.{k}.{i}": m for k, ms in moments(opt).items() for i, m in enumerate(ms[:2])})
    out["trainable"] = opt.trainable_mask().clone()
    return out


@pytest.mark.parametrize("masked", [False, True])
@pytest.mark.parametrize("n_split", [0, 3, 4])  # 4: row 4 is also cloned
def test_clone_and_split_is_duplicate_then_split_in_one_surgery(masked, n_split):
    """The reference is the two primitives one after the other (as the rules called them): the
    same rows in the same order, parameters, Adam moments, extras, state and random draws, bit for bit."""
    n = 16
    trainable = (torch.arange(n) % 3 != 0) if masked else None
    clone = torch.zeros(n, dtype=torch.bool)
    clone[[0, 4, 5, 9]] = True
    split_mask = torch.zeros(n, dtype=torch.bool)
    split_mask[[2, 10, 15, 4][:n_split]] = True
    results = []
    for one_surgery in (False, True):
        torch.manual_seed(0)  # warm's extras["relevance"]
        opt = warm(trainable, n)
        state = {"acc": torch.arange(n, dtype=torch.float32) + 0.5, "seen": torch.arange(n) % 4}
        gen = torch.Generator().manual_seed(3)
        if one_surgery:
            counts = clone_and_split(opt, clone, split_mask, state, gen)
        else:
            cloned = duplicate(opt, clone, state)
            counts = (cloned, split(opt, torch.cat([split_mask, split_mask.new_zeros(cloned)]), state, gen))
        results.append((counts, _snapshot(opt, state), torch.rand(1, generator=gen)))
    (c_ref, snap_ref, rng_ref), (c_got, snap_got, rng_got) = results
    assert c_got == c_ref == (4, n_split) and torch.equal(rng_got, rng_ref)
    assert snap_got.keys() == snap_ref.keys()
    for k in snap_ref:
        assert torch.equal(snap_got[k], snap_ref[k]), k
    assert len(snap_got["param.means"]) == n + 4 + n_split
