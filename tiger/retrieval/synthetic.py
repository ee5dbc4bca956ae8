"""A synthetic labelled scene for testing retrieval without model weights.

Several objects (clusters of Gaussians) with known labels sit on a floor; each label has a fixed
unit D-dim embedding and a CLIP-space (F-dim) embedding that the scene's PCA maps onto it exactly,
so a :class:`DictTextEncoder` can stand in for CLIP. "Oracle" feature maps are renders of each
Gaussian's label embedding, i.e. what a perfect feature extractor would give.
"""
from __future__ import annotations

import math
import types
from dataclasses import dataclass
from typing import Sequence

import torch

from .text import CANONICAL_NEGATIVES

DEFAULT_LABELS = ("red mug", "teddy bear", "green apple", "blue book")


class DictTextEncoder:
    """``encode_text`` from a fixed table {text: [F] embedding}; unknown texts are an error."""

    def __init__(self, table: dict[str, torch.Tensor]) -> None:
        self.table = {k: torch.as_tensor(v, dtype=torch.float32) for k, v in table.items()}

    def encode_text(self, texts: Sequence[str]) -> torch.Tensor:
        missing = [t for t in texts if t not in self.table]
        if missing:
            raise KeyError(f"DictTextEncoder: no embedding for {missing}")
        return torch.stack([self.table[t] for t in texts])


@dataclass
class LabelledScene:
    """scene: namespace with means, quats, scales, opacities, colors [N, 3], lang=None,
    lang_pca_basis [F, D], lang_pca_mean [F]; labels: names (index = label id, the last is the
    floor); label_of: [N] label id per Gaussian; label_lang: [K, D] unit embeddings; cameras:
    namespaces with viewmat, K, width, height, image_name; encoder: text -> [F]."""

    scene: types.SimpleNamespace
    labels: list
    label_of: torch.Tensor
    label_lang: torch.Tensor
    cameras: list
    encoder: DictTextEncoder


def look_at(eye: Sequence[float], target: Sequence[float], up: Sequence[float] = (0.0, 0.0, 1.0)) -> torch.Tensor:
    """World->camera [4, 4] (OpenCV axes: +x right, +y down, +z forward) looking from eye at target."""
    eye_t = torch.tensor(eye, dtype=torch.float64)
    f = torch.tensor(target, dtype=torch.float64) - eye_t
    f = f / f.norm()
    r = torch.linalg.cross(f, torch.tensor(up, dtype=torch.float64))
    r = r / r.norm()
    d = torch.linalg.cross(f, r)
    R = torch.stack([r, d, f])
    V = torch.eye(4, dtype=torch.float64)
    V[:3, :3] = R
    V[:3, 3] = -R @ eye_t
    return V


def make_labelled_scene(labels: Sequence[str] = DEFAULT_LABELS, *, per_object: int = 40, floor: int = 80,
                        views: int = 8, size: int = 48, dim: int = 64, clip_dim: int = 512,
                        seed: int = 0) -> LabelledScene:
    """Objects on a ring around the origin (radius 0.6), a floor under them, ``views`` cameras on a
    higher ring looking at the origin (fov ~ 60 deg, ``size`` x ``size`` px). Float32."""
    g = torch.Generator().manual_seed(seed)
    k = len(labels)
    names = list(labels) + ["floor"]
    means, scales, label_of = [], [], []
    for i in range(k):
        a = 2 * math.pi * i / k
        centre = torch.tensor([0.6 * math.cos(a), 0.6 * math.sin(a), 0.18])
        means.append(centre + 0.12 * (torch.rand(per_object, 3, generator=g) * 2 - 1))
        scales.append(torch.full((per_object, 3), 0.05) * (0.7 + 0.6 * torch.rand(per_object, 1, generator=g)))
        label_of.append(torch.full((per_object,), i))
    fl = torch.rand(floor, 3, generator=g) * 2.4 - 1.2
    fl[:, 2] = 0.0
    means.append(fl)
    scales.append(torch.tensor([0.14, 0.14, 0.01]).expand(floor, 3) * (0.8 + 0.4 * torch.rand(floor, 1, generator=g)))
    label_of.append(torch.full((floor,), k))
    means_t = torch.cat(means)
    n = means_t.shape[0]
    label_t = torch.cat(label_of)
    quats = torch.nn.functional.normalize(torch.randn(n, 4, generator=g), dim=1)
    quats[label_t == k] = torch.tensor([1.0, 0.0, 0.0, 0.0])
    opac = 0.7 + 0.25 * torch.rand(n, generator=g)
    palette = torch.rand(k + 1, 3, generator=g)

    # Language space: unit label embeddings; CLIP space: mean + basis @ l + a part the PCA drops.
    label_lang = torch.nn.functional.normalize(torch.randn(k + 1, dim, generator=g, dtype=torch.float64), dim=1)
    q, _ = torch.linalg.qr(torch.randn(clip_dim, clip_dim, generator=g, dtype=torch.float64))
    basis, ortho = q[:, :dim], q[:, dim:]
    mean = 0.05 * torch.randn(clip_dim, generator=g, dtype=torch.float64)

    def clip_vec(l: torch.Tensor) -> torch.Tensor:
        extra = ortho @ (0.3 * torch.randn(clip_dim - dim, generator=g, dtype=torch.float64))
        return mean + basis @ l + extra

    table = {name: clip_vec(label_lang[i]) for i, name in enumerate(names)}
    for neg in CANONICAL_NEGATIVES:
        table[neg] = clip_vec(torch.nn.functional.normalize(torch.randn(dim, generator=g, dtype=torch.float64), dim=0))

    fy = 0.5 * size / math.tan(math.radians(30))
    K = torch.tensor([[fy, 0.0, size / 2], [0.0, fy, size / 2], [0.0, 0.0, 1.0]], dtype=torch.float64)
    cams = []
    for v in range(views):
        a = 2 * math.pi * (v + 0.5) / views
        eye = (2.2 * math.cos(a), 2.2 * math.sin(a), 1.6)
        cams.append(types.SimpleNamespace(viewmat=look_at(eye, (0.0, 0.0, 0.1)), K=K.clone(), width=size,
                                          height=size, image_name=f"frame_{v + 1:05d}.png"))
    scene = types.SimpleNamespace(means=means_t, quats=quats, scales=torch.cat(scales), opacities=opac,
                                  colors=palette[label_t], lang=None, lang_pca_basis=basis.float(),
                                  lang_pca_mean=mean.float())
    return LabelledScene(scene=scene, labels=names, label_of=label_t, label_lang=label_lang.float(),
                         cameras=cams, encoder=DictTextEncoder({kk: v.float() for kk, v in table.items()}))


def oracle_feature_maps(ls: LabelledScene, min_alpha: float = 0.5) -> list:
    """Per view ``(features [H, W, D], valid [H, W])``: renders of each Gaussian's label embedding;
    pixels with alpha < ``min_alpha`` are invalid (they stand for pixels in no SAM mask)."""
    from tiger import rasterize_gaussians

    s = ls.scene
    maps = []
    with torch.no_grad():
        for cam in ls.cameras:
            out = rasterize_gaussians(s.means, s.quats, s.scales, s.opacities, ls.label_lang[ls.label_of],
                                      cam.viewmat.float(), cam.K.float(), cam.width, cam.height)
            maps.append((out["color"], out["alpha"] >= min_alpha))
    return maps


def label_masks(ls: LabelledScene, camera: object, min_alpha: float = 0.5) -> torch.Tensor:
    """[K+1, H, W] bool: pixels where label k carries the largest share of the rendered weight."""
    from tiger import rasterize_gaussians

    s = ls.scene
    onehot = torch.nn.functional.one_hot(ls.label_of, len(ls.labels)).float()
    with torch.no_grad():
        out = rasterize_gaussians(s.means, s.quats, s.scales, s.opacities, onehot,
                                  camera.viewmat.float(), camera.K.float(), camera.width, camera.height)
    share = out["color"]
    best = share.argmax(dim=2)
    ok = out["alpha"] >= min_alpha
    return torch.stack([(best == i) & ok for i in range(len(ls.labels))])
