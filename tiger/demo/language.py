"""Demo stages after rendering: language embedding of the tabletop scene and text queries.

Per-pixel language supervision is built the way TIGER's pipeline shapes it (SPEC §4): every
object mask carries one CLIP-space vector (the masked average), the maps are reduced to 64-d
with a PCA fitted over all views, and each Gaussian's 64-d L starts from the lift (its
blending-weighted mean of the maps) and is then trained through the features-only backward, as
``tiger embed`` does by default. Where the real pipeline gets each mask's vector from MaskCLIP + SAM on
photographs, the demo takes it from the object's name: CLIP's text tower when CLIP weights are
configured (so free-form queries such as "coffee cup" work through CLIP), otherwise fixed
built-in embeddings of the label names and a few synonyms.
"""
from __future__ import annotations

import logging
from pathlib import Path
from typing import Optional, Sequence

import torch

from tiger.language.field import FieldResult, train_field
from tiger.language.lift import lift
from tiger.language.pca import StreamingPCA
from tiger.render import Camera
from tiger.render.views import orbit_cameras
from tiger.retrieval import retrieve, write_relevancy_pictures
from tiger.retrieval.text import EmbeddingTable, TextEncoder
from tiger.scene.labelled import LabelledScene
from tiger.utils.images import save_png
from tiger.utils.io import file_slug

from .scene import DEMO_ORBIT

log = logging.getLogger(__name__)

SYNONYMS = {
    "table": ["table", "the table", "wooden table", "desk"],
    "mug": ["mug", "a mug", "cup", "coffee cup", "coffee mug"],
    "ball": ["ball", "a ball", "blue ball", "beach ball"],
    "box": ["box", "a box", "cardboard box", "package"],
    "plant": ["plant", "a plant", "potted plant", "leaves"],
}


def builtin_text_table(names: Sequence[str], dim: int = 512, seed: int = 7) -> EmbeddingTable:
    """The demo's vocabulary without CLIP: one fixed random unit vector per label (dimension 512,
    like CLIP ViT-B/16), shared by its synonyms, plus LERF's canonical negatives; texts are
    looked up case-folded, other texts are an error that lists the known words."""
    g = torch.Generator().manual_seed(seed)
    vecs = torch.nn.functional.normalize(torch.randn(len(names), dim, generator=g), dim=1)
    table = {}
    for name, v in zip(names, vecs):
        for word in SYNONYMS.get(name, [name]):
            table[word] = v
    table.update({w: torch.nn.functional.normalize(torch.randn(dim, generator=g), dim=0)
                  for w in ("object", "things", "stuff", "texture")})
    return EmbeddingTable(table, source="the demo's built-in vocabulary", fold_case=True,
                          hint="; configure CLIP weights to query freely")


def load_text_encoder(names: Sequence[str], models: Optional[str] = None) -> tuple[TextEncoder, str]:
    """(encoder, description): CLIP's text tower when its weights are found, else built-in."""
    try:
        from tiger.language.maskclip import MaskCLIP
        from tiger.models.paths import ModelNotFoundError, resolve_model_path
    except ImportError as e:  # transformers missing
        return builtin_text_table(names), f"built-in label embeddings ({e})"
    try:
        path = resolve_model_path("clip", models)
    except ModelNotFoundError:
        return builtin_text_table(names), (
            "CLIP weights not configured (put openai/clip-vit-base-patch16 under $TIGER_MODELS or "
            "pass --models): using the scene's built-in label embeddings")
    return MaskCLIP.from_pretrained(path), f"CLIP text encoder from {path}"


def label_feature_maps(scene: LabelledScene, label_vecs: torch.Tensor, cameras: Sequence[Camera],
                       pca_dim: int = 64) -> tuple[list[dict], tuple[torch.Tensor, torch.Tensor]]:
    """Per view: each pixel takes the CLIP-space vector of the object it shows (one vector per
    object mask, i.e. the masked average), reduced to ``pca_dim`` with a PCA over all views.

    Returns ([{"features" [H,W,D], "valid" [H,W]}], (basis [F,D], mean [F])).
    """
    per_view, pca = [], StreamingPCA(label_vecs.shape[1], pca_dim)
    for cam in cameras:
        label, alpha = scene.label_image(cam)
        valid = alpha > 0.5
        counts = torch.bincount(label[valid], minlength=len(scene.names)).double()
        pca.update(label_vecs, weights=counts)  # each mask's vector, weighted by its pixels
        per_view.append((label, valid))
    basis = pca.fit()
    proj = basis.project(label_vecs)  # [K, D]
    maps = [{"features": proj[label] * valid[..., None], "valid": valid} for label, valid in per_view]
    return maps, (basis.components, basis.mean)


#: A Gaussian whose blending weights over all the training views' valid pixels sum to less than
#: this (pixels at the maps' size) keeps its lifted embedding after training.
MIN_TRAINED_WEIGHT = 0.2


def train_demo_field(scene: LabelledScene, label_vecs: torch.Tensor, cameras: Sequence[Camera], *,
                     steps: int = 300, progress: bool = True) -> FieldResult:
    """Train the language field of ``scene`` (in place: ``scene.scene.lang`` and its PCA) from the
    label feature maps of ``cameras``, the way ``tiger embed`` does by default: every Gaussian
    starts from its lifted embedding (:func:`tiger.language.lift.lift`), then L is trained.

    Why the lift and not a random start: the demo's views look down on the table, so its
    underside, and the table top under each object, reach the pixels only through one or two
    opaque layers (summed blending weight ~1e-3 px). The training's gradient there is tiny; from a
    random start such a Gaussian keeps its random feature, which no threshold can tell from a
    real one (a third of the table scored anywhere in [-0.3, 0.7] for "table"). The lift gives it
    the features of what covers it in the views: the surface above, or the object's own front.
    Gaussians that reach no valid pixel at all stay at 0 (no language evidence).

    Training cannot improve on the lift where the views hardly see a Gaussian: its gradient is
    its blending weight times the residual, and Adam normalises even a 1e-6 gradient into a
    full-size step, so 300 steps walk it away from what its pixels show (norms up to 2.7 where
    the seen ones have 0.4-1.3). Gaussians whose summed weight is below
    :data:`MIN_TRAINED_WEIGHT` keep their lifted embedding.

    Args:
        scene: the labelled scene; label_vecs: [K, F] one CLIP-space vector per label.
        cameras: the training views; steps: training steps (2 views each, lr 0.02, L1).
    """
    maps, pca = label_feature_maps(scene, label_vecs, cameras)
    lifted = lift(scene.scene, cameras, maps)
    scene.scene.lang = lifted.lang.clone()
    res = train_field(scene.scene, cameras, maps, steps=steps, lr=0.02, batch_views=2, loss="l1",
                      progress=progress, pca=pca, init="keep")
    weak = lifted.weight < MIN_TRAINED_WEIGHT
    lang = scene.scene.lang
    lang[weak] = lifted.lang[weak].to(lang)
    res.lang = lang
    return res


def embed_and_query(scene: LabelledScene, out: Path, queries: Sequence[str], timer,
                    models: Optional[str] = None, train_size=(160, 120), n_train_views: int = 8,
                    steps: int = 300, picture_size=(480, 360), tau: float = 0.5) -> list[dict]:
    """Train the language field of ``scene`` and answer ``queries``; writes pictures and PLYs."""
    with timer.stage("text encoder"):
        encoder, how = load_text_encoder(scene.names, models)
    print(f"  text encoder: {how}")
    with timer.stage("label embeddings of the objects"):
        texts = [SYNONYMS.get(n, [n])[0] for n in scene.names]
        label_vecs = encoder.encode_text(texts).float()
    cams = orbit_cameras(n_train_views, *train_size, start_deg=5.0, names="train{}", **DEMO_ORBIT)
    field_scene = scene.scene
    with timer.stage(f"language feature maps ({n_train_views} views, PCA 512->64), lift, "
                     f"train language field ({steps} steps, features-only backward)"):
        res = train_demo_field(scene, label_vecs, cams, steps=steps)
    print(f"  field: loss {res.losses[0]:.4f} -> {res.losses[-1]:.4f}; {res.coverage()}")
    with timer.stage("save scene.ply (with lang_* and PCA) and the text-embedding table"):
        field_scene.metadata.update({"source": "tiger demo", "labels": list(scene.names)})
        field_scene.save_ply(out / "scene.ply")
        builtin = isinstance(encoder, EmbeddingTable)
        if builtin:
            encoder.save(out / "text_embeddings.pt")

    pic_cams = orbit_cameras(4, *picture_size, start_deg=20.0, names="view{}", **DEMO_ORBIT)
    results = []
    for q in queries:
        with timer.stage(f"query '{q}'"):
            # Cosine cut at 0.5: the demo's objects sit near 0.85 with their own name and below
            # 0.3 with the others' (Otsu's automatic cut splits off the table first here).
            r = retrieve(field_scene, q, encoder=encoder, score="cosine", tau=tau)
            # LERF's relevancy needs real canonical negatives ("object", "stuff", ...): with the
            # built-in vocabulary the heat maps show the cosine instead.
            views = _views_showing(scene, r.mask, pic_cams)
            write_relevancy_pictures(field_scene, views[:2], q, out / "relevancy",
                                     encoder=encoder, score="cosine" if builtin else "relevancy")
            _write_selection(scene, r.mask, views[0], out / f"retrieved_{file_slug(q)}.png")
            _write_highlight(scene, r.mask, views[0], out / f"highlight_{file_slug(q)}.png")
        results.append(_report(scene, q, r))
    return results


def _views_showing(scene: LabelledScene, mask: torch.Tensor, cams: Sequence[Camera]) -> list[Camera]:
    """The cameras ordered by how much of the selection they see (visible alpha of it)."""
    sel = mask.to(scene.scene.dtype)[:, None]
    seen = []
    for cam in cams:
        with torch.no_grad():  # a quarter-size render is enough to compare views
            r = scene.scene.render(cam.resized(cam.width // 4, cam.height // 4), sel)
        seen.append(float(r["color"].sum()))
    order = sorted(range(len(cams)), key=lambda i: -seen[i])
    return [cams[i] for i in order]


def _write_selection(scene: LabelledScene, mask: torch.Tensor, cam: Camera, path: Path) -> None:
    with torch.no_grad():
        r = scene.scene.subset(mask).render(cam, background=torch.ones(3))
    save_png(path, r["color"])


def _write_highlight(scene: LabelledScene, mask: torch.Tensor, cam: Camera, path: Path) -> None:
    """The whole scene with the selection tinted orange and everything else greyed out."""
    rgb = scene.scene.rgb
    grey = rgb.mean(1, keepdim=True).expand(-1, 3) * 0.6 + 0.2
    tint = torch.where(mask[:, None], 0.45 * rgb + 0.55 * torch.tensor([1.0, 0.5, 0.0]), grey)
    with torch.no_grad():
        r = scene.scene.render(cam, tint, background=torch.ones(3))
    save_png(path, r["color"])


def _report(scene: LabelledScene, query: str, r) -> dict:
    sel = r.mask
    best = int(torch.bincount(scene.labels[sel], minlength=len(scene.names)).argmax()) if r.count else -1
    truth = scene.labels == best
    tp = int((sel & truth).sum())
    prec = tp / max(int(sel.sum()), 1)
    rec = tp / max(int(truth.sum()), 1)
    name = scene.names[best] if best >= 0 else "(nothing)"
    print(f"  '{query}': {r.count} Gaussians selected (tau={r.tau:.3f}) -> mostly '{name}', "
          f"precision {prec:.3f}, recall {rec:.3f} against that object's labels")
    return {"query": query, "object": name, "selected": r.count, "tau": r.tau,
            "precision": prec, "recall": rec}
