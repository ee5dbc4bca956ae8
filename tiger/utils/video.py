"""Frames → MP4 (OpenCV, else imageio-ffmpeg) or animated GIF (Pillow), written atomically."""
from __future__ import annotations

import contextlib
import logging
import os
from pathlib import Path
from typing import Optional, Sequence, Union

import numpy as np
from torch import Tensor

from .images import to_uint8
from .io import atomic_write

log = logging.getLogger(__name__)

KINDS = ("auto", "mp4", "gif", "none")
Frame = Union[Tensor, np.ndarray]


def _frames_uint8(frames: Sequence[Frame]) -> list[np.ndarray]:
    arrays = [to_uint8(f) for f in frames]
    if not arrays:
        raise ValueError("write_video: frames is empty")
    shape = arrays[0].shape
    if len(shape) != 3 or shape[2] != 3:
        raise ValueError(f"write_video: frames must be [H, W, 3], got {list(shape)}")
    for k, a in enumerate(arrays):
        if a.shape != shape:
            raise ValueError(f"write_video: frame {k} has shape {list(a.shape)}, frame 0 has {list(shape)}")
    return arrays


def _mp4_opencv(arrays: list[np.ndarray], tmp: Path, fps: float) -> None:
    import cv2

    h, w = arrays[0].shape[:2]
    writer = cv2.VideoWriter(str(tmp), cv2.VideoWriter_fourcc(*"mp4v"), float(fps), (w, h))
    if not writer.isOpened():
        raise RuntimeError("OpenCV has no MP4 encoder in this build")
    try:
        for a in arrays:
            writer.write(np.ascontiguousarray(a[:, :, ::-1]))  # OpenCV wants BGR
    finally:
        writer.release()


def _mp4_imageio(arrays: list[np.ndarray], tmp: Path, fps: float) -> None:
    import imageio.v2 as imageio  # needs the imageio-ffmpeg plugin

    with imageio.get_writer(str(tmp), fps=fps, codec="libx264", macro_block_size=1) as w:
        for a in arrays:
            w.append_data(a)


def _write_mp4(arrays: list[np.ndarray], path: Path, fps: float) -> None:
    errors = []
    for writer in (_mp4_opencv, _mp4_imageio):
        tmp = path.with_name(f".{path.stem}.tmp.mp4")  # the suffix tells the encoder the container
        try:
            writer(arrays, tmp, fps)
            if not tmp.is_file() or tmp.stat().st_size == 0:
                raise RuntimeError("the encoder wrote nothing")
            os.replace(tmp, path)
            return
        except Exception as exc:  # noqa: BLE001 - try the next backend, report all at the end
            errors.append(f"{writer.__name__[5:]}: {exc}")
        finally:
            with contextlib.suppress(FileNotFoundError):
                tmp.unlink()
    raise RuntimeError("cannot write MP4 (" + "; ".join(errors) + "); install opencv-python-headless "
                       "or imageio + imageio-ffmpeg, or ask for a GIF")


def write_video(frames: Sequence[Frame], path_stem: Union[str, os.PathLike], fps: float = 12,
                kind: str = "auto") -> Optional[Path]:
    """Write ``frames`` ([H, W, 3] float in [0, 1] or uint8, all the same size) as a video.

    ``kind``: "mp4" (OpenCV's encoder, else imageio-ffmpeg; an error when neither works), "gif"
    (Pillow), "auto" (MP4, falling back to GIF) or "none". The file is ``path_stem`` plus the
    suffix, written through a temporary file and a rename. Returns its path (None for "none").
    """
    if kind not in KINDS:
        raise ValueError(f"write_video: kind must be one of {KINDS}, got {kind!r}")
    if fps <= 0:
        raise ValueError(f"write_video: fps must be positive, got {fps}")
    if kind == "none":
        return None
    arrays = _frames_uint8(frames)
    stem = Path(path_stem)
    stem.parent.mkdir(parents=True, exist_ok=True)
    if kind in ("auto", "mp4"):
        path = stem.with_name(stem.name + ".mp4")
        try:
            _write_mp4(arrays, path, fps)
            return path
        except RuntimeError as exc:
            if kind == "mp4":
                raise
            log.info("%s: writing an animated GIF instead", exc)
    from PIL import Image

    path = stem.with_name(stem.name + ".gif")
    images = [Image.fromarray(a) for a in arrays]
    with atomic_write(path, "wb") as fh:
        images[0].save(fh, format="GIF", save_all=True, append_images=images[1:],
                       duration=max(1, round(1000 / fps)), loop=0)
    return path
