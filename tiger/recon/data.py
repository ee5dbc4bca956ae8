"""Loading a dataset's views for training: undistorted, downscaled images + cameras."""
from __future__ import annotations

import os
from typing import Optional, Sequence, Union

import torch

from tiger.render import Camera
from tiger.scene.images import load_image

PathLike = Union[str, os.PathLike]


def load_views(cameras: Sequence[Camera], downscale: float = 1.0, cache_dir: Optional[PathLike] = None,
               background: Optional[tuple] = None, progress: bool = False) -> tuple:
    """(pinhole cameras at 1/downscale, images [h, w, 3] float32 in [0, 1]) for ``cameras``.

    Distorted images are undistorted once and cached (see :func:`tiger.scene.images.load_image`).
    """
    from tqdm.auto import tqdm

    cams, imgs = [], []
    for cam in tqdm(cameras, desc="loading images", disable=not progress):
        img, c = load_image(cam, downscale, cache_dir=cache_dir, background=background)
        cams.append(c)
        imgs.append(img)
    return cams, imgs
