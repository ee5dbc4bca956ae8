"""Posed-image datasets: COLMAP folders and NeRF/instant-ngp ``transforms.json``.

``load_dataset(path)`` recognises
  * a COLMAP folder (``sparse/0``, ``sparse`` or the folder itself holding
    ``cameras.{bin,txt}``; images in ``images/``),
  * a ``transforms.json`` file or a folder holding one (instant-ngp, nerfstudio),
  * a NeRF-synthetic folder (``transforms_train.json`` + ``transforms_test.json``,
    which also fix the train/test split).
"""
from __future__ import annotations

import logging
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Optional, Sequence, Union

import torch

from tiger.render import Camera
from .colmap import colmap_cameras, find_model_dir, read_model
from .errors import MissingImagesError, SceneFormatError
from .nerf import load_transforms

log = logging.getLogger(__name__)
PathLike = Union[str, os.PathLike]


@dataclass
class SceneDataset:
    """Cameras of a capture (sorted by image name), its sparse points when known, and
    where it came from.

    Attributes:
        cameras: every camera, sorted by ``image_name``.
        points: [P, 3] float32 sparse points (COLMAP) or None.
        point_colors: [P, 3] float32 RGB in [0, 1] or None.
        source: the path the dataset was loaded from.
        kind: ``"colmap"`` or ``"nerf"``.
        test_names: image names of the test views when the dataset fixes the split.
    """

    cameras: list
    points: Optional[torch.Tensor] = None
    point_colors: Optional[torch.Tensor] = None
    source: Path = Path(".")
    kind: str = ""
    test_names: Optional[set] = None
    metadata: dict = field(default_factory=dict)

    def split(self, test_every: int = 8) -> tuple:
        """(train cameras, test cameras). INRIA's rule: every ``test_every``-th camera in
        name order (indices 0, 8, 16, ...) is a test view; ``test_every <= 0`` puts all in
        train. A split fixed by the dataset (NeRF-synthetic) takes precedence."""
        if self.test_names is not None:
            return ([c for c in self.cameras if c.image_name not in self.test_names],
                    [c for c in self.cameras if c.image_name in self.test_names])
        if test_every <= 0:
            return list(self.cameras), []
        return ([c for i, c in enumerate(self.cameras) if i % test_every != 0],
                [c for i, c in enumerate(self.cameras) if i % test_every == 0])


def load_dataset(path: PathLike, images: str = "images", skip_missing: bool = False) -> SceneDataset:
    """Load a COLMAP or NeRF dataset (see the module docstring).

    Args:
        path: dataset folder or ``transforms*.json`` file.
        images: COLMAP image folder, relative to ``path``.
        skip_missing: drop views whose image file is missing (warning) instead of raising.
    """
    path = Path(path)
    if not path.exists():
        raise SceneFormatError(path, "dataset path does not exist")
    if path.is_file():
        cams, extra = load_transforms(path, skip_missing)
        return SceneDataset(cams, source=path, kind="nerf", metadata=extra)
    if (path / "transforms_train.json").is_file():
        train, extra = load_transforms(path / "transforms_train.json", skip_missing)
        test_file = path / "transforms_test.json"
        test = load_transforms(test_file, skip_missing)[0] if test_file.is_file() else []
        for c in test:  # names are relative paths, so train/ and test/ never collide
            c.metadata["split"] = "test"
        cams = sorted(train + test, key=lambda c: c.image_name)
        return SceneDataset(cams, source=path, kind="nerf", test_names={c.image_name for c in test},
                            metadata=extra)
    if (path / "transforms.json").is_file():
        cams, extra = load_transforms(path / "transforms.json", skip_missing)
        return SceneDataset(cams, source=path, kind="nerf", metadata=extra)
    if not any((d / f"cameras.{e}").is_file() for d in (path, path / "sparse" / "0", path / "sparse")
               for e in ("bin", "txt")):
        raise SceneFormatError(path, "no dataset found: looked for a NeRF / instant-ngp transforms.json "
                                     "(or transforms_train.json) and a COLMAP model (cameras.bin or "
                                     "cameras.txt in ., sparse/0 or sparse)")
    return load_colmap(path, images, skip_missing)


def load_colmap(path: PathLike, images: str = "images", skip_missing: bool = False) -> SceneDataset:
    """A COLMAP dataset: model from ``sparse/0`` (or similar), images from ``path/images``."""
    path = Path(path)
    model_dir = find_model_dir(path)
    cams_c, imgs_c, pts = read_model(model_dir)
    images_dir = path / images
    cams = colmap_cameras(cams_c, imgs_c, images_dir, model_dir)
    missing = [c for c in cams if not c.image_path.is_file()]
    if missing:
        if not skip_missing:
            raise MissingImagesError(images_dir, [str(c.image_name) for c in missing], len(cams))
        log.warning("%s: skipped %d of %d images that are missing (first: %s)", images_dir, len(missing),
                    len(cams), missing[0].image_name)
        cams = [c for c in cams if c.image_path.is_file()]
    if not cams:
        raise SceneFormatError(model_dir, "no registered images")
    points = colors = None
    if pts is not None and len(pts.xyz):
        points = torch.from_numpy(pts.xyz).float()
        colors = torch.from_numpy(pts.rgb).float() / 255.0
    return SceneDataset(cams, points, colors, source=path, kind="colmap")


def look_at_point(cameras: Sequence[Camera]) -> torch.Tensor:
    """[3] least-squares point closest to all optical axes (what the cameras look at).

    Falls back to the mean camera centre when the axes are (nearly) parallel.
    """
    cameras = [c.to("cpu", torch.float64) for c in cameras]
    A = torch.zeros(3, 3, dtype=torch.float64)
    b = torch.zeros(3, dtype=torch.float64)
    for c in cameras:
        o = c.center.double()
        d = c.viewmat[2, :3].double()  # camera +z (forward) in world coordinates
        d = d / d.norm()
        P = torch.eye(3, dtype=torch.float64) - torch.outer(d, d)
        A += P
        b += P @ o
    ev = torch.linalg.eigvalsh(A)
    if float(ev[0]) < 1e-3 * float(ev[-1]):
        return torch.stack([c.center.double() for c in cameras]).mean(0)
    return torch.linalg.solve(A, b)


def points_in_views(cameras: Sequence[Camera], n: int, min_fraction: float = 0.5,
                    generator: Optional[torch.Generator] = None, max_rounds: int = 50,
                    radius_fraction: float = 1.0) -> torch.Tensor:
    """[n, 3] random points seen (in front of the camera and inside the image) by at
    least ``min_fraction`` of ``cameras``: INRIA's random initialisation, restricted to the
    region the captures share (a visual hull of the frusta, without silhouettes).

    Candidates are drawn uniformly in a cube around :func:`look_at_point` whose half-size
    is ``radius_fraction`` x the largest camera distance from it, and kept by rejection.
    (Points near the cameras cover much of their images: a smaller fraction keeps the
    first steps cheap when the object sits in the middle of the captures.)
    """
    if not cameras:
        raise ValueError("tiger: points_in_views needs cameras")
    cameras = [c.to("cpu", torch.float64) for c in cameras]
    centre = look_at_point(cameras)
    half = float(torch.stack([c.center.double() for c in cameras]).sub(centre).norm(dim=1).max())
    half = (half if half > 0 else 1.0) * radius_fraction
    need = max(1, int(round(min_fraction * len(cameras))))
    kept: list = []
    total = 0
    for _ in range(max_rounds):
        cand = centre + (torch.rand((max(4 * n, 4096), 3), generator=generator, dtype=torch.float64) * 2 - 1) * half
        seen = torch.zeros(cand.shape[0], dtype=torch.int64)
        for c in cameras:
            uv, z = c.project(cand)
            seen += ((z > 0) & (uv[:, 0] >= 0) & (uv[:, 0] < c.width) & (uv[:, 1] >= 0) & (uv[:, 1] < c.height)).long()
        good = cand[seen >= need]
        kept.append(good)
        total += good.shape[0]
        if total >= n:
            break
    if total == 0:
        raise ValueError("tiger: no region is seen by enough cameras for a random initialisation; "
                         "lower min_fraction")
    pts = torch.cat(kept)
    if pts.shape[0] < n:
        idx = torch.randint(0, pts.shape[0], (n,), generator=generator)
        pts = pts[idx]
    return pts[:n].float()
