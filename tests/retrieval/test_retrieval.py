"""Text -> PCA -> relevance -> selection -> bounds, and heat-map pictures (no training here)."""
from __future__ import annotations

import math
import types

import pytest
import torch

from tiger.retrieval import (CANONICAL_NEGATIVES, choose_tau, embed_queries, min_error_threshold, otsu_threshold,
                             valley_threshold,
                             pca_of, project,
                             relevancy, retrieve, robust_bounds, save_heatmap)
from tiger.testing.labelled_scene import make_labelled_scene


def test_project_matches_definition():
    g = torch.Generator().manual_seed(0)
    basis, mean = torch.randn(512, 64, generator=g), torch.randn(512, generator=g)
    e = torch.randn(3, 512, generator=g)
    want = torch.nn.functional.normalize((e.double() - mean.double()) @ basis.double(), dim=1)
    torch.testing.assert_close(project(e, basis, mean).double(), want, atol=1e-6, rtol=0)
    # Every way of handing over the PCA gives the same vectors.
    pcabasis = types.SimpleNamespace(components=basis, mean=mean)
    scene = types.SimpleNamespace(lang_pca_basis=basis, lang_pca_mean=mean)
    for src in [(basis, mean), {"basis": basis, "mean": mean}, pcabasis, scene]:
        torch.testing.assert_close(embed_queries(e, dim=64, pca=src), project(e, basis, mean))
    with pytest.raises(ValueError, match="no PCA basis"):
        embed_queries(e, dim=64)
    with pytest.raises(ValueError, match="needs a text encoder"):
        embed_queries("a cup", dim=64, pca=(basis, mean))
    with pytest.raises(ValueError, match="PCA mean must be"):
        pca_of((basis, torch.zeros(3)))
    # A D-dim embedding is used as it is (normalised).
    v = torch.randn(64, generator=g)
    torch.testing.assert_close(embed_queries(v, dim=64), torch.nn.functional.normalize(v[None], dim=1))


def test_text_encoder_path_and_templates_are_the_encoders_business():
    ls = make_labelled_scene(views=1, per_object=4, floor=4)
    q = embed_queries(["red mug", "floor"], dim=64, encoder=ls.encoder, pca=ls.scene)
    torch.testing.assert_close(q, ls.label_lang[[0, len(ls.labelled.names) - 1]], atol=1e-5, rtol=0)
    with pytest.raises(KeyError, match="no embedding"):
        embed_queries("a unicorn", dim=64, encoder=ls.encoder, pca=ls.scene)


def test_relevancy_wrapper_shapes_and_checks():
    f = torch.randn(4, 5, 8)
    cos, rel = relevancy(f, torch.randn(8), torch.randn(3, 8))
    assert cos.shape == (4, 5, 1) and rel.shape == (4, 5, 1)
    cos, rel = relevancy(f, torch.randn(2, 8))
    assert cos.shape == (4, 5, 2) and rel is None
    f[1, 2, 3] = float("nan")
    with pytest.raises(ValueError, match="NaN or Inf"):
        relevancy(f, torch.randn(8))
    with pytest.raises(ValueError, match="positives must be"):
        relevancy(torch.randn(3, 8), torch.randn(7))


def test_otsu_separates_two_groups():
    g = torch.Generator().manual_seed(1)
    s = torch.cat([0.05 * torch.randn(900, generator=g), 0.8 + 0.05 * torch.randn(100, generator=g)])
    t = otsu_threshold(s)
    assert 0.15 < t < 0.65  # Otsu leans toward the larger class, but separates them
    assert int((s > t).sum()) == 100
    assert otsu_threshold(torch.full((5,), 0.3)) == pytest.approx(0.3)  # nothing to separate
    assert choose_tau(s, 0.25, "cosine") == 0.25
    with pytest.raises(ValueError, match="tau must be"):
        choose_tau(s, "median", "cosine")
    assert choose_tau(s, "otsu", "cosine") == t
    # Relevancy: the cut is never below 0.5.
    assert choose_tau(torch.tensor([0.1, 0.2, 0.3, 0.31]), "auto", "relevancy") >= 0.5


@pytest.mark.parametrize("fraction", [0.3, 0.01, 0.001])
def test_auto_threshold_survives_small_objects(fraction):
    # An object that is 1 % (or 0.1 %) of the scene: Otsu cuts inside the background, the
    # default rule (minimum-error split, cut in the valley between the modes) still separates.
    g = torch.Generator().manual_seed(7)
    n = 100_000
    k = int(n * fraction)
    background = 0.1 + 0.08 * torch.randn(n - k, generator=g)
    obj = 0.7 + 0.05 * torch.randn(k, generator=g)
    s = torch.cat([background, obj])
    t = choose_tau(s, "auto", "cosine")
    assert t == valley_threshold(s)
    assert 0.35 < t < 0.6  # in the valley between 0.1 +- 0.08 and 0.7 +- 0.05
    fp, tp = int((background > t).sum()), int((obj > t).sum())
    assert tp / k >= 0.999 and tp / (tp + fp) >= 0.999, (t, tp, fp)
    if fraction <= 0.01:
        t_otsu = otsu_threshold(s)
        assert int((background > t_otsu).sum()) > 10 * k  # why Otsu is not the default
    # The same in relevancy terms (sigmoid(10 * margin)).
    r = torch.sigmoid(10 * (s - 0.2))
    tr = choose_tau(r, "auto", "relevancy")
    assert tr >= 0.5 and int(((r > tr) != (s > t)).sum()) <= 2


def test_valley_rule_keeps_an_objects_tail():
    # Object scores: a tight peak near 1 and a tail down to 0.5 (Gaussians blended at its border);
    # background: two clusters. Kittler-Illingworth splits off the tight peak and loses the tail;
    # the valley rule cuts in the empty stretch between background and object.
    g = torch.Generator().manual_seed(8)
    bg = torch.cat([-0.2 + 0.04 * torch.randn(120, generator=g), 0.1 + 0.04 * torch.randn(120, generator=g)])
    obj = torch.cat([0.97 + 0.01 * torch.randn(33, generator=g), torch.linspace(0.5, 0.9, 7)])
    s = torch.cat([bg, obj])
    t = valley_threshold(s)
    assert bg.max() < t < 0.5
    assert min_error_threshold(s) > 0.5  # the failure the valley search fixes
    assert valley_threshold(torch.full((4,), 0.2)) == pytest.approx(0.2)


def test_robust_bounds_ignore_outliers():
    g = torch.Generator().manual_seed(2)
    pts = torch.rand(1000, 3, generator=g) * 2 - 1 + torch.tensor([5.0, 0.0, -2.0])
    pts[:10] = torch.tensor([100.0, -100.0, 50.0])  # 1 % stray Gaussians
    c, lo, hi = robust_bounds(pts, (0.02, 0.98))
    assert torch.allclose(c, torch.tensor([5.0, 0.0, -2.0], dtype=torch.float64), atol=0.1)
    assert (lo > torch.tensor([3.9, -1.1, -3.1], dtype=torch.float64)).all()
    assert (hi < torch.tensor([6.1, 1.1, -0.9], dtype=torch.float64)).all()
    torch.testing.assert_close(lo, torch.quantile(pts.double(), 0.02, dim=0))
    with pytest.raises(ValueError, match="quantiles"):
        robust_bounds(pts, (0.9, 0.1))


def _scene_with_oracle_lang(noise: float = 0.3, seed: int = 3):
    ls = make_labelled_scene(views=2)
    g = torch.Generator().manual_seed(seed)
    lang = ls.label_lang[ls.labelled.labels] + noise * torch.randn(len(ls.labelled.labels), 64, generator=g) / 8
    ls.scene.lang = lang
    return ls


@pytest.mark.parametrize("score", ["cosine", "relevancy"])
def test_retrieve_each_label_exactly(score):
    ls = _scene_with_oracle_lang()
    for i, name in enumerate(ls.labelled.names):
        r = retrieve(ls.scene, name, encoder=ls.encoder, score=score)
        gt = ls.labelled.labels == i
        assert torch.equal(r.mask, gt), (name, r.tau)
        c_true = torch.quantile(ls.scene.means[gt].double(), 0.5, dim=0)
        torch.testing.assert_close(r.center, c_true)
        assert (r.bbox_min <= r.center).all() and (r.center <= r.bbox_max).all()
        sub = r.subscene(ls.scene)
        assert sub.means.shape[0] == int(gt.sum()) and torch.equal(sub.lang, ls.scene.lang[gt])
        if score == "relevancy":
            assert r.relevancy is not None and r.tau >= 0.5


def test_retrieve_from_embeddings_and_tensors():
    ls = _scene_with_oracle_lang()
    e = ls.encoder.encode_text(["teddy bear"])[0]
    r1 = retrieve(ls.scene, e)  # a CLIP-space embedding, projected with the scene's PCA
    r2 = retrieve(ls.scene.lang, ls.label_lang[1], tau=0.5)  # plain tensors
    assert torch.equal(r1.mask, ls.labelled.labels == 1) and torch.equal(r2.mask, ls.labelled.labels == 1)
    assert r2.center is None and r1.relevancy is None
    negs = ls.encoder.encode_text(list(CANONICAL_NEGATIVES))
    r3 = retrieve(ls.scene, e, negatives=negs, score="relevancy")
    assert torch.equal(r3.mask, ls.labelled.labels == 1)
    with pytest.raises(ValueError, match="needs negatives"):
        retrieve(ls.scene, e, score="relevancy")
    with pytest.raises(ValueError, match="no language features"):
        retrieve(types.SimpleNamespace(lang=None), e)
    with pytest.raises(ValueError, match="one query"):
        retrieve(ls.scene, ["red mug", "floor"], encoder=ls.encoder)
    # A query matching nothing selects nothing (and says so) instead of failing.
    ls.scene.lang = torch.zeros_like(ls.scene.lang)
    r4 = retrieve(ls.scene, e)
    assert r4.count == 0 and r4.center is None


def test_heatmap_picture(tmp_path):
    h, w = 30, 40
    v = torch.linspace(0, 1, h * w).reshape(h, w)
    img = torch.rand(h, w, 3)
    p = save_heatmap(tmp_path / "a" / "heat.png", v, img, title="t", vmin=0.5, vmax=1, below=0.5,
                     boxes=[[1, 2, 10, 12]], points=[[5, 5]])
    from PIL import Image

    with Image.open(p) as im:
        assert im.size[0] > w and im.size[1] > h
    with pytest.raises(ValueError, match="does not match"):
        save_heatmap(tmp_path / "b.png", v, torch.rand(h + 1, w, 3))


def test_relevancy_maps_render_and_pictures(tmp_path):
    from tiger.retrieval import relevancy_maps, write_relevancy_pictures

    ls = _scene_with_oracle_lang(noise=0.0)
    cam = ls.cameras[0]
    q = embed_queries(["red mug"], dim=64, encoder=ls.encoder, pca=ls.scene)
    m = relevancy_maps(ls.scene, cam, q)
    assert m["cosine"].shape == (1, cam.height, cam.width) and m["relevancy"] is None
    # Where the mug dominates the render, the rendered feature is (nearly) its embedding.
    from tiger.testing.labelled_scene import label_masks

    mug = label_masks(ls, cam)[0]
    assert mug.sum() > 10 and m["cosine"][0][mug].median() > 0.9
    paths = write_relevancy_pictures(ls.scene, ls.cameras, "red mug", tmp_path, encoder=ls.encoder)
    assert len(paths) == 2 and all(p.stat().st_size > 1000 for p in paths)


def test_relevancy_picture_reads_high_at_the_target(tmp_path):
    """The heat map is drawn alone beside the render: at the target it is the colour map's colour
    of the target's score (high end), not that colour blended over the object's own colour; where
    no Gaussian is, it is black, not the colour of the score of empty space."""
    import matplotlib
    import numpy as np
    from PIL import Image

    from tiger.retrieval import relevancy_maps, write_relevancy_pictures
    from tiger.retrieval.maps import GAP, TITLE_H
    from tiger.testing.labelled_scene import label_masks

    ls = _scene_with_oracle_lang(noise=0.0)
    cam = ls.cameras[0]
    target = ls.labelled.names.index("red mug")
    p, = write_relevancy_pictures(ls.scene, [cam], "red mug", tmp_path, encoder=ls.encoder, score="cosine")
    q = embed_queries(["red mug"], dim=64, encoder=ls.encoder, pca=ls.scene)
    m = relevancy_maps(ls.scene, cam, q)
    h, w = cam.height, cam.width
    pic = np.asarray(Image.open(p).convert("RGB")).astype(np.float64)
    heat = pic[TITLE_H:TITLE_H + h, w + GAP:2 * w + GAP]
    mug = label_masks(ls, cam)[target].numpy()
    cos = m["cosine"][0].numpy()
    expect = matplotlib.colormaps["turbo"](np.clip((cos + 1) / 2, 0, 1))[..., :3] * 255
    assert mug.sum() > 10
    assert np.abs(heat[mug] - expect[mug]).max() <= 1.0
    high = matplotlib.colormaps["turbo"](0.95)[:3]
    assert np.abs(heat[mug].mean(0) / 255 - high).max() < 0.15  # reads as the top of the bar
    empty = m["alpha"].numpy() < 0.5
    assert empty.sum() > 10 and (heat[empty] == 0).all()
    # the left panel is the render itself
    from tiger.scene import render_rgb

    rgb = render_rgb(ls.scene, [cam])[0].numpy() * 255
    assert np.abs(pic[TITLE_H:TITLE_H + h, :w] - rgb).max() <= 1.0


@pytest.mark.cuda
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_retrieve_on_cuda_matches_cpu():
    import tiger

    if not tiger.ops.cuda_enabled():
        pytest.skip("tiger built without CUDA kernels")
    ls = _scene_with_oracle_lang()
    cpu = retrieve(ls.scene, "green apple", encoder=ls.encoder, score="relevancy")
    gpu_scene = ls.scene.to("cuda")
    for dt in (torch.float32, torch.float16):
        gpu_scene.lang = ls.scene.lang.to("cuda", dt)
        gpu = retrieve(gpu_scene, "green apple", encoder=ls.encoder, score="relevancy")
        assert gpu.scores.is_cuda
        torch.testing.assert_close(gpu.cosine.cpu(), cpu.cosine, atol=2e-3 if dt == torch.float16 else 1e-5, rtol=0)
        assert torch.equal(gpu.mask.cpu(), cpu.mask)
        torch.testing.assert_close(gpu.center.cpu(), cpu.center, atol=1e-5, rtol=0)


def test_pictures_and_retrieval_with_a_gaussian_scene(tmp_path):
    from tiger.retrieval import write_relevancy_pictures
    from tiger.scene import render_rgb
    from tiger.scene import GaussianScene

    ls = _scene_with_oracle_lang()
    gs = ls.scene
    r = retrieve(gs, "blue book", encoder=ls.encoder, score="relevancy")
    assert torch.equal(r.mask, ls.labelled.labels == 3)
    sub = r.subscene(gs)
    assert isinstance(sub, GaussianScene) and len(sub) == int(r.mask.sum())
    rgb = render_rgb(gs, [ls.cameras[0]])[0]  # SH colour through the rasterizer
    # degree-0 SH colour is the palette colour: the same picture as rendering the colours as channels
    flat = gs.render(ls.cameras[0], (gs.sh_dc * (0.5 / math.sqrt(math.pi)) + 0.5).clamp_min(0))["color"]
    torch.testing.assert_close(rgb, flat.clamp(0, 1), atol=1e-6, rtol=0)
    assert rgb.shape == (48, 48, 3) and float(rgb.max()) > 0.2
    paths = write_relevancy_pictures(gs, ls.cameras[:1], "blue book", tmp_path, encoder=ls.encoder)
    assert paths[0].stat().st_size > 1000
