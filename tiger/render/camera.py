"""Pinhole cameras (OpenCV axes) and the lens distortion of the images they index.

A :class:`Camera` is what the rasterizer needs: a world-to-camera 4x4 matrix with
OpenCV axes (+x right, +y down, +z forward), intrinsics ``K`` in pixels (pixel centres
at +0.5, as COLMAP and the rasterizer), and the image size. ``distortion`` describes
the lens of the *image file*; the image loader undistorts it so that the returned
pixels follow the pinhole model of ``K``.
"""
from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Optional

import torch

from .rasterize import camera_center

__all__ = ["Camera", "Distortion", "rigid_inverse"]


@dataclass(frozen=True)
class Distortion:
    """OpenCV lens distortion of normalised image coordinates (x, y) = (X/Z, Y/Z).

    radial = (1 + k1 r² + k2 r⁴ + k3 r⁶) / (1 + k4 r² + k5 r⁴ + k6 r⁶)
    x_d = x·radial + 2 p1 x y + p2 (r² + 2x²);  y_d = y·radial + p1 (r² + 2y²) + 2 p2 x y
    Every COLMAP model handled here (SIMPLE_RADIAL, RADIAL, OPENCV, FULL_OPENCV) and the
    instant-ngp/nerfstudio ``k1 k2 k3 p1 p2`` fields are special cases.
    """

    k1: float = 0.0
    k2: float = 0.0
    p1: float = 0.0
    p2: float = 0.0
    k3: float = 0.0
    k4: float = 0.0
    k5: float = 0.0
    k6: float = 0.0

    def __post_init__(self) -> None:
        for f in dataclasses.fields(self):
            v = getattr(self, f.name)
            if not math.isfinite(float(v)):
                raise ValueError(f"tiger: distortion coefficient {f.name} must be finite, got {v}")

    @property
    def is_identity(self) -> bool:
        return all(getattr(self, f.name) == 0.0 for f in dataclasses.fields(self))

    def as_tuple(self) -> tuple:
        return tuple(float(getattr(self, f.name)) for f in dataclasses.fields(self))


@dataclass
class Camera:
    """One posed pinhole view.

    Attributes:
        viewmat: [4, 4] world-to-camera transform, OpenCV axes.
        K: [3, 3] intrinsics in pixels (fx, fy, cx, cy; no skew).
        width, height: image size in pixels.
        image_path: the image file (None for purely virtual views).
        image_name: a stable name (the file name relative to the dataset's image folder).
        distortion: lens distortion of ``image_path`` (None: the file is already pinhole).
        camera_id: the intrinsics group in the source dataset, when it has one.
    """

    viewmat: torch.Tensor
    K: torch.Tensor
    width: int
    height: int
    image_path: Optional[Path] = None
    image_name: str = ""
    distortion: Optional[Distortion] = None
    camera_id: Optional[int] = None
    metadata: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.viewmat = torch.as_tensor(self.viewmat)
        self.K = torch.as_tensor(self.K)
        if not self.viewmat.is_floating_point():
            self.viewmat = self.viewmat.double()
        if not self.K.is_floating_point():
            self.K = self.K.double()
        name = self.image_name or "camera"
        if self.viewmat.shape != (4, 4):
            raise ValueError(f"tiger: {name}: viewmat must be [4, 4], got {list(self.viewmat.shape)}")
        if self.K.shape != (3, 3):
            raise ValueError(f"tiger: {name}: K must be [3, 3], got {list(self.K.shape)}")
        if not (torch.isfinite(self.viewmat).all() and torch.isfinite(self.K).all()):
            raise ValueError(f"tiger: {name}: viewmat and K must be finite")
        self.width, self.height = int(self.width), int(self.height)
        if self.width <= 0 or self.height <= 0:
            raise ValueError(f"tiger: {name}: image size must be positive, got {self.width}x{self.height}")
        if not (self.K[0, 0] > 0 and self.K[1, 1] > 0):
            raise ValueError(f"tiger: {name}: focal lengths must be positive, got "
                             f"fx={float(self.K[0, 0])}, fy={float(self.K[1, 1])}")
        if self.image_path is not None:
            self.image_path = Path(self.image_path)
        if self.distortion is not None and self.distortion.is_identity:
            self.distortion = None

    # -- intrinsics -------------------------------------------------------------------
    @property
    def fx(self) -> float:
        return float(self.K[0, 0])

    @property
    def fy(self) -> float:
        return float(self.K[1, 1])

    @property
    def cx(self) -> float:
        return float(self.K[0, 2])

    @property
    def cy(self) -> float:
        return float(self.K[1, 2])

    @property
    def fov_x(self) -> float:
        """Horizontal field of view in radians."""
        return 2.0 * math.atan(0.5 * self.width / self.fx)

    @property
    def fov_y(self) -> float:
        return 2.0 * math.atan(0.5 * self.height / self.fy)

    # -- pose -------------------------------------------------------------------------
    @property
    def c2w(self) -> torch.Tensor:
        """[4, 4] camera-to-world transform (OpenCV axes)."""
        return rigid_inverse(self.viewmat)

    @property
    def center(self) -> torch.Tensor:
        """[3] camera centre in world coordinates."""
        return camera_center(self.viewmat)

    def world_to_camera(self, points: torch.Tensor) -> torch.Tensor:
        """[P, 3] world points -> [P, 3] camera-space points (OpenCV axes)."""
        vm = self.viewmat.to(points)
        return points @ vm[:3, :3].T + vm[:3, 3]

    def project(self, points: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Pinhole projection of [P, 3] world points.

        Returns (uv [P, 2] in pixels, pixel centres at +0.5; depth [P] = camera z).
        Points with z <= 0 get non-finite or meaningless uv: test ``depth > 0``.
        """
        pc = self.world_to_camera(points)
        z = pc[:, 2]
        K = self.K.to(points)
        uv = torch.stack([K[0, 0] * pc[:, 0] / z + K[0, 2], K[1, 1] * pc[:, 1] / z + K[1, 2]], -1)
        return uv, z

    # -- derived cameras ----------------------------------------------------------------
    def scaled(self, factor: float) -> "Camera":
        """The same view downscaled by ``factor`` (> 0): size rounded, K scaled exactly
        by the ratio of the new to the old size (pixel centres stay at +0.5)."""
        if not factor > 0:
            raise ValueError(f"tiger: downscale factor must be positive, got {factor}")
        if factor == 1:
            return dataclasses.replace(self)
        return self.resized(max(1, int(round(self.width / factor))),
                            max(1, int(round(self.height / factor))))

    def resized(self, width: int, height: int) -> "Camera":
        """The same view at ``width x height`` pixels: K's rows scaled by the size ratios (pixel
        centres stay at +0.5)."""
        if (width, height) == (self.width, self.height):
            return dataclasses.replace(self)
        K = self.K.clone()
        K[0] *= width / self.width
        K[1] *= height / self.height
        K[2] = torch.tensor([0.0, 0.0, 1.0], dtype=K.dtype)
        return dataclasses.replace(self, K=K, width=width, height=height)

    def to(self, device: Optional[torch.device | str] = None,
           dtype: Optional[torch.dtype] = None) -> "Camera":
        """This camera with viewmat and K on ``device`` in ``dtype``; itself when they already
        are (like ``Tensor.to``: no copy, and no re-validation, which would read device values back)."""
        viewmat, K = self.viewmat.to(device=device, dtype=dtype), self.K.to(device=device, dtype=dtype)
        if viewmat is self.viewmat and K is self.K:
            return self
        return dataclasses.replace(self, viewmat=viewmat, K=K)


def rigid_inverse(T: torch.Tensor) -> torch.Tensor:
    """Inverse of a [4, 4] rotation+translation transform (exact, no general inverse)."""
    R, t = T[:3, :3], T[:3, 3]
    out = torch.eye(4, dtype=T.dtype, device=T.device)
    out[:3, :3] = R.T
    out[:3, 3] = -R.T @ t
    return out
