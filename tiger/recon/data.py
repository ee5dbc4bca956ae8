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
    The images are decoded on a few threads (JPEG decoding, resampling and undistortion release
    the GIL); the result is in the cameras' order whatever the threads' order.
    """
    from tiger.utils.progress import progress as progress_lines
    from tiger.utils.threads import thread_map

    bar = progress_lines(len(cameras), "loading images", disable=not progress)
    out = thread_map(lambda cam: load_image(cam, downscale, cache_dir=cache_dir, background=background), cameras,
                     min(8, os.cpu_count() or 1), "tiger-load-views", on_done=lambda: bar.update(1))
    bar.close()
    return [c for _, c in out], [img for img, _ in out]


def valid_pixel_masks(cameras: Sequence[Camera], downscale: float = 1.0) -> Optional[list]:
    """Per camera, [h, w] bool: the pixels of its image as :func:`load_views` makes it that hold
    captured colour, i.e. not the black border that undistortion leaves (see
    :func:`tiger.scene.images.undistortion_valid_mask`). ``None`` when no camera has lens
    distortion: every pixel counts, and the loss and the metric need no mask."""
    from tiger.scene.images import undistortion_valid_mask

    if all(c.distortion is None for c in cameras):
        return None
    return [undistortion_valid_mask(c, downscale) for c in cameras]


def masked_fraction(masks: Optional[Sequence[torch.Tensor]]) -> float:
    """Share of the pixels left out by ``masks`` (0 for None)."""
    if not masks:
        return 0.0
    total = sum(m.numel() for m in masks)
    return float(sum(int((~m).sum()) for m in masks)) / max(total, 1)


def transparent_images(cameras: Sequence[Camera]) -> list[str]:
    """Names of the cameras whose image file has transparent pixels (an alpha channel not
    opaque everywhere; :func:`tiger.scene.images.image_has_transparency`). Those pixels are
    composited over a fixed background when the images load; opaque photographs give []."""
    from tiger.scene.images import image_has_transparency

    return [c.image_name for c in cameras if c.image_path is not None and image_has_transparency(c.image_path)]


def training_background(transparent: Sequence[str], requested: Optional[bool] = None) -> tuple[bool, str]:
    """Whether training renders over a random colour each step, and why (one line).

    The rule: a random background when no image has transparent pixels (opaque photographs:
    every pixel shows a surface, so a Gaussian that leaves a see-through gap is always wrong,
    whatever the background colour; a fixed black one would let dark surfaces be learned as
    gaps). Images with transparency were composited over black when loaded, so their black
    is a target the renders must match over black: they train over black. ``requested``
    (True / False) overrides the rule.

    Args:
        transparent: names of the images with transparent pixels (:func:`transparent_images`).
        requested: None for the rule, else the user's choice.
    Returns:
        (random_background, description for the run's printout and metrics.json).
    """
    n = len(transparent)
    if requested is None:
        if n == 0:
            return True, "random colour each training step (no image has transparent pixels)"
        return False, (f"black ({n} image{'s' if n != 1 else ''} with transparent pixels, e.g. "
                       f"{transparent[0]}, composited over black)")
    if requested:
        if n:
            return True, (f"random colour each training step (asked for; {n} image{'s' if n != 1 else ''} "
                          "with transparent pixels were composited over black, which the renders now "
                          "learn as colour)")
        return True, "random colour each training step (asked for)"
    return False, "black (asked for)"
