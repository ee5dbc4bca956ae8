"""A synthetic labelled scene for testing retrieval without model weights.

Several objects (clusters of Gaussians) with known labels sit on a floor; each label has a fixed
unit D-dim embedding and a CLIP-space (F-dim) embedding that the scene's PCA maps onto it exactly,
so a :class:`~tiger.retrieval.text.EmbeddingTable` can stand in for CLIP. "Oracle" feature maps are renders of each
Gaussian's label embedding, i.e. what a perfect feature extractor would give.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence

import torch

from tiger.render.views import look_at
from tiger.render import Camera
from tiger.scene import GaussianScene
from tiger.scene.labelled import LabelledScene

from tiger.retrieval.text import CANONICAL_NEGATIVES, EmbeddingTable

DEFAULT_LABELS = ("red mug", "teddy bear", "green apple", "blue book")


@dataclass
class SyntheticRetrievalScene:
    """A labelled scene with what retrieval needs to be tested without weights.

    Attributes:
        labelled: the Gaussians (``lang`` None, the PCA basis [F, D] / mean [F] set) and their
            labels; ``names`` end with "floor".
        label_lang: [K, D] unit language embedding per label.
        cameras: the views.
        encoder: text -> [F] CLIP-space embedding of every label and canonical negative.
    """

    labelled: LabelledScene
    label_lang: torch.Tensor
    cameras: list[Camera]
    encoder: EmbeddingTable

    @property
    def scene(self) -> GaussianScene:
        return self.labelled.scene


def make_labelled_scene(labels: Sequence[str] = DEFAULT_LABELS, *, per_object: int = 40, floor: int = 80,
                        views: int = 8, size: int = 48, dim: int = 64, clip_dim: int = 512,
                        seed: int = 0) -> SyntheticRetrievalScene:
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
        cams.append(Camera(look_at(eye, (0.0, 0.0, 0.1), up=(0.0, 0.0, 1.0)), K.clone(), size, size,
                           image_name=f"frame_{v + 1:05d}.png"))
    scene = GaussianScene.from_values(means_t, quats, torch.cat(scales), opac, palette[label_t])
    scene.lang_pca_basis, scene.lang_pca_mean = basis.float(), mean.float()
    return SyntheticRetrievalScene(LabelledScene(scene, label_t, names), label_lang.float(), cams,
                                   EmbeddingTable({kk: v.float() for kk, v in table.items()},
                                                  source="the synthetic scene's text table"))


def oracle_feature_maps(ls: SyntheticRetrievalScene, min_alpha: float = 0.5) -> list:
    """Per view ``(features [H, W, D], valid [H, W])``: renders of each Gaussian's label embedding;
    pixels with alpha < ``min_alpha`` are invalid (they stand for pixels in no SAM mask)."""
    lang = ls.label_lang.to(ls.scene.device)[ls.labelled.labels.to(ls.scene.device)]
    maps = []
    with torch.no_grad():
        for cam in ls.cameras:
            out = ls.scene.render(cam, lang)
            maps.append((out["color"], out["alpha"] >= min_alpha))
    return maps


def label_masks(ls: SyntheticRetrievalScene, camera: Camera, min_alpha: float = 0.5) -> torch.Tensor:
    """[K+1, H, W] bool: pixels where label k carries the largest share of the rendered weight."""
    best, alpha = ls.labelled.label_image(camera)
    ok = alpha >= min_alpha
    return torch.stack([(best == i) & ok for i in range(len(ls.labelled.names))])
