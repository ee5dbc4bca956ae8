"""Training-free lifting: against a brute-force float64 accumulation of the blending weights
(the dense reference renderer), and as a retrieval method / field initialisation on the
synthetic labelled scene."""
from __future__ import annotations

import math

import pytest
import torch

import tiger.ops
from tiger.language.field import train_field
from tiger.language.lift import lift, lift_features
from tiger.render.reference import render_ref
from tiger.render.views import look_at
from tiger.retrieval import retrieve
from tiger.testing.labelled_scene import make_labelled_scene, oracle_feature_maps
from tiger.render import Camera
from tiger.scene import GaussianScene

DEVICES = ["cpu"] + (["cuda"] if torch.cuda.is_available() and tiger.ops.cuda_enabled() else [])


def small_case(device, dtype=torch.float64, n=150, d=5, views=3, seed=0):
    g = torch.Generator().manual_seed(seed)
    means = torch.rand(n, 3, generator=g, dtype=torch.float64) * 1.6 - 0.8
    means[:4] = torch.tensor([0.0, 0.0, 40.0], dtype=torch.float64)  # above every camera: seen by none
    quats = torch.nn.functional.normalize(torch.randn(n, 4, generator=g, dtype=torch.float64), dim=1)
    scales = 0.03 + 0.12 * torch.rand(n, 3, generator=g, dtype=torch.float64)
    opac = 0.2 + 0.75 * torch.rand(n, generator=g, dtype=torch.float64)
    scene = GaussianScene.from_values(means, quats, scales, opac, torch.rand(n, 3, generator=g, dtype=torch.float64))
    cams, maps = [], []
    for v in range(views):
        a = 2 * math.pi * v / views
        w, h = 36 + 4 * v, 28
        f = 0.6 * w
        K = torch.tensor([[f, 0, w / 2], [0, f, h / 2], [0, 0, 1]], dtype=torch.float64)
        cams.append(Camera(look_at((3 * math.cos(a), 3 * math.sin(a), 1.0), (0.0, 0.0, 0.0), up=(0.0, 0.0, 1.0)),
                           K, w, h, image_name=f"v{v}.png"))
        # maps at half the camera's size (the camera is rescaled to the map), a quarter invalid
        mh, mw = h // 2, w // 2
        maps.append((torch.randn(mh, mw, d, generator=g, dtype=torch.float64),
                     torch.rand(mh, mw, generator=g) > 0.25))
    return scene.to(device, dtype), cams, maps


def brute_force(scene, cams, maps):
    """sum_v sum_p w_ip F_v(p) / sum_v sum_p w_ip by the dense float64 reference (one-hot colours)."""
    s = scene.to("cpu", torch.float64)
    n, d = len(s), maps[0][0].shape[-1]
    num, den = torch.zeros(n, d, dtype=torch.float64), torch.zeros(n, dtype=torch.float64)
    eye = torch.eye(n, dtype=torch.float64)
    for cam, (feats, valid) in zip(cams, maps):
        h, w = feats.shape[:2]
        c = cam.resized(w, h)
        out = render_ref(s.means, s.quats, s.scales, s.opacities, eye, c.viewmat.double(), c.K.double(), w, h)
        weights = out["color"][valid.cpu()]  # [P, N] blending weight of every Gaussian at each valid pixel
        num += weights.T @ feats.cpu().double()[valid.cpu()]
        den += weights.sum(0)
    return num, den


@pytest.mark.parametrize("device", DEVICES)
def test_float64_matches_brute_force(device):
    scene, cams, maps = small_case(device)
    res = lift(scene, cams, maps)
    num, den = brute_force(scene, cams, maps)
    assert res.lang.device.type == device and res.lang.shape == num.shape
    assert int((den > 0).sum()) > 0.5 * len(den) and int((den == 0).sum()) > 0  # both kinds present
    torch.testing.assert_close(res.weight.cpu(), den, rtol=1e-10, atol=1e-12)
    want = torch.where(den[:, None] > 0, num / den.clamp_min(1e-300)[:, None], torch.zeros_like(num))
    torch.testing.assert_close(res.lang.cpu(), want, rtol=1e-9, atol=1e-10)
    assert "reach no valid pixel" in res.coverage()


@pytest.mark.parametrize("device", DEVICES)
def test_float32_close_to_brute_force(device):
    scene, cams, maps = small_case(device, torch.float32, seed=1)
    maps32 = [(f.float(), m) for f, m in maps]
    got = lift_features(scene, cams, maps32)
    num, den = brute_force(scene, cams, maps)
    seen = den > 1e-3
    want = num[seen] / den[seen, None]
    assert got.dtype == torch.float32
    torch.testing.assert_close(got.cpu().double()[seen], want, rtol=1e-4, atol=1e-4)


def test_bad_inputs_are_named():
    scene, cams, maps = small_case("cpu")
    with pytest.raises(ValueError, match="no cameras"):
        lift(scene, [], maps)
    with pytest.raises(ValueError, match="feature map 1 has 4 channels, map 0 has 5"):
        lift(scene, cams, [maps[0], (maps[1][0][..., :4], maps[1][1]), maps[2]])
    with pytest.raises(ValueError, match="2 feature maps for 3 cameras"):
        lift(scene, cams, maps[:2])


def precision_recall(ls):
    out = []
    for i, name in enumerate(ls.labelled.names):
        r = retrieve(ls.scene, name, encoder=ls.encoder)
        gt = ls.labelled.labels == i
        tp = int((r.mask & gt).sum())
        out.append((tp / max(r.count, 1), tp / int(gt.sum())))
    return out


def test_lift_initialises_the_field_on_the_synthetic_scene():
    ls = make_labelled_scene()
    maps = oracle_feature_maps(ls)
    pca = (ls.scene.lang_pca_basis, ls.scene.lang_pca_mean)
    lifted = lift(ls.scene, ls.cameras, maps)
    assert int((lifted.weight <= 0).sum()) == 0
    ls.scene.lang, ls.scene.lang_pca_basis, ls.scene.lang_pca_mean = lifted.lang, *pca
    lift_only = precision_recall(ls)
    # lifted embeddings start where random ones need many steps to get to: 20 steps from the
    # lift beat 20 steps from random, and reach the retrieval bar
    losses = {}
    for init in ("lift", "random"):
        ls.scene.lang = lifted.lang.clone() if init == "lift" else None
        res = train_field(ls.scene, ls.cameras, maps, steps=20, init="keep" if init == "lift" else "random",
                          pca=pca, lr=0.05, batch_views=2, progress=False)
        losses[init] = res.losses
    assert losses["lift"][0] < 0.5 * losses["random"][0]
    assert losses["lift"][-1] < losses["random"][-1]
    # lift + 20 steps reaches the same precision/recall bar as 60 steps of training from random
    ls.scene.lang = lifted.lang.clone()
    train_field(ls.scene, ls.cameras, maps, steps=20, init="keep", pca=pca, lr=0.05, batch_views=2, progress=False)
    for (p, r), name in zip(precision_recall(ls), ls.labelled.names):
        assert p >= 0.95 and r >= 0.95, (name, p, r)
    assert all(0.0 <= p <= 1.0 and 0.0 <= r <= 1.0 for p, r in lift_only)
