"""A Gaussian scene whose Gaussians each carry an object label (synthetic and demo scenes)."""
from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import torch
from torch import Tensor

from tiger.render import Camera
from .gaussian_scene import GaussianScene

__all__ = ["LabelledScene"]


@dataclass
class LabelledScene:
    """A :class:`GaussianScene` plus one object label per Gaussian.

    Attributes:
        scene: the Gaussians (N of them).
        labels: [N] int64, each Gaussian's index into ``names``.
        names: the object names, K of them.
    """

    scene: GaussianScene
    labels: Tensor
    names: list[str]

    def __post_init__(self) -> None:
        n = len(self.scene)
        if self.labels.shape != (n,) or self.labels.dtype != torch.int64:
            raise ValueError(f"tiger: LabelledScene.labels must be [N={n}] int64, got "
                             f"{list(self.labels.shape)} {self.labels.dtype}")
        self.names = list(self.names)
        if n and (int(self.labels.min()) < 0 or int(self.labels.max()) >= len(self.names)):
            raise ValueError(f"tiger: LabelledScene.labels must index the {len(self.names)} names, "
                             f"got values in [{int(self.labels.min())}, {int(self.labels.max())}]")

    def __len__(self) -> int:
        return len(self.scene)

    def subset(self, mask: Tensor) -> "LabelledScene":
        """The Gaussians selected by ``mask`` ([N] bool or 1-D indices), labels and names kept."""
        mask = torch.as_tensor(mask, device=self.scene.device)
        return LabelledScene(self.scene.subset(mask), self.labels[mask.to(self.labels.device)],
                             self.names)

    @staticmethod
    def concat(parts: Sequence["LabelledScene"], names: Sequence[str]) -> "LabelledScene":
        """All Gaussians of ``parts`` in order; their labels index ``names``."""
        return LabelledScene(GaussianScene.concat([p.scene for p in parts]),
                             torch.cat([p.labels for p in parts]), list(names))

    def one_hot(self) -> Tensor:
        """[N, K] per-Gaussian indicator of its label, in the scene's dtype (a colour to render)."""
        return torch.nn.functional.one_hot(self.labels, len(self.names)).to(
            device=self.scene.device, dtype=self.scene.dtype)

    def label_image(self, camera: Camera) -> tuple[Tensor, Tensor]:
        """(label [H, W] int64, alpha [H, W]): at each pixel the label carrying the largest share
        of the rendered weight, and the pixel's total opacity."""
        with torch.no_grad():
            out = self.scene.render(camera, self.one_hot())
        return out["color"].argmax(dim=2), out["alpha"]
