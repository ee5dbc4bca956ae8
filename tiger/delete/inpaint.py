"""Image inpainters for object deletion: OpenCV (Telea, built in) and LaMa (``big-lama`` TorchScript).

Every inpainter is a callable ``inpainter(images, masks) -> images``:
    images [B, 3, H, W] float in [0, 1], masks [B, 1, H, W] (nonzero = fill), any device;
    the result has the input's shape, dtype and device, and equals the input exactly outside the
    mask (only masked pixels are replaced).
"""
from __future__ import annotations

import logging
import os
from pathlib import Path
from typing import Optional, Protocol, Union

import numpy as np
import torch

log = logging.getLogger(__name__)

PathLike = Union[str, os.PathLike]


class Inpainter(Protocol):
    """``inpainter(images [B,3,H,W] in [0,1], masks [B,1,H,W]) -> [B,3,H,W]``; see the module docstring."""

    name: str

    def __call__(self, images: torch.Tensor, masks: torch.Tensor) -> torch.Tensor: ...


def check_inpaint_inputs(images: torch.Tensor, masks: torch.Tensor, who: str) -> torch.Tensor:
    """Validate an inpainter's inputs; return the mask as bool [B, 1, H, W]."""
    if not isinstance(images, torch.Tensor) or images.ndim != 4 or images.shape[1] != 3:
        shape = list(images.shape) if isinstance(images, torch.Tensor) else type(images).__name__
        raise ValueError(f"tiger.delete.{who}: images must be [B, 3, H, W], got {shape}")
    if not images.is_floating_point():
        raise ValueError(f"tiger.delete.{who}: images must be float in [0, 1], got {images.dtype}")
    b, _, h, w = images.shape
    if not isinstance(masks, torch.Tensor) or tuple(masks.shape) != (b, 1, h, w):
        shape = list(masks.shape) if isinstance(masks, torch.Tensor) else type(masks).__name__
        raise ValueError(f"tiger.delete.{who}: masks must be [B={b}, 1, H={h}, W={w}], got {shape}")
    if not bool(torch.isfinite(images).all()):
        raise ValueError(f"tiger.delete.{who}: images contain NaN or Inf")
    return masks.to(images.device) != 0


def paste(images: torch.Tensor, filled: torch.Tensor, masks: torch.Tensor) -> torch.Tensor:
    """``filled`` inside ``masks`` (bool [B,1,H,W]), ``images`` exactly outside."""
    return torch.where(masks, filled.to(images.dtype), images)


class OpenCVInpainter:
    """OpenCV's inpainting (Telea's fast marching by default), the built-in inpainter.

    Each channel is inpainted as a float32 image (``cv2.inpaint`` accepts 1-channel float), so
    nothing is quantised to 8 bits. OpenCV's float path is not scale-invariant (on values in
    [0, 1] it overshoots wildly), so each channel is mapped to [0, 255] from its known range
    first and back afterwards. ``radius`` is the neighbourhood in pixels.
    """

    def __init__(self, radius: float = 5.0, method: str = "telea") -> None:
        if method not in ("telea", "ns"):
            raise ValueError(f"tiger.delete.OpenCVInpainter: method must be 'telea' or 'ns', got {method!r}")
        if not radius > 0:
            raise ValueError(f"tiger.delete.OpenCVInpainter: radius must be > 0, got {radius}")
        self.radius, self.method = float(radius), method
        self.name = f"opencv-{method}"

    def fill_channels(self, values: np.ndarray, mask: np.ndarray) -> np.ndarray:
        """values [H, W, C] float32, mask [H, W] bool → [H, W, C] float32 inpainted per channel."""
        from tiger.utils.lazy import require

        cv2 = require("cv2", "opencv-python-headless", "OpenCV inpainting")
        flag = cv2.INPAINT_TELEA if self.method == "telea" else cv2.INPAINT_NS
        m8 = mask.astype(np.uint8)
        if not m8.any():
            return values.copy()
        out = values.astype(np.float32, copy=True)
        known = ~mask.astype(bool)
        if not known.any():
            return out
        for c in range(values.shape[2]):
            ch = out[..., c]
            lo, hi = float(ch[known].min()), float(ch[known].max())
            span = hi - lo if hi > lo else 1.0
            scaled = np.ascontiguousarray((ch - lo) * (255.0 / span), dtype=np.float32)
            filled = cv2.inpaint(scaled, m8, self.radius, flag)
            out[..., c] = np.where(known, ch, filled * (span / 255.0) + lo)
        return out

    def __call__(self, images: torch.Tensor, masks: torch.Tensor) -> torch.Tensor:
        m = check_inpaint_inputs(images, masks, "OpenCVInpainter")
        arr = images.detach().permute(0, 2, 3, 1).float().cpu().numpy()
        mk = m[:, 0].cpu().numpy()
        filled = np.stack([self.fill_channels(a, k) for a, k in zip(arr, mk)])
        filled_t = torch.from_numpy(filled).permute(0, 3, 1, 2).to(images.device)
        return paste(images, filled_t.clamp(0, 1), m)


def symmetric_pad_index(n: int, pad: int, device: Optional[torch.device] = None) -> torch.Tensor:
    """Source indices of a length-``n`` axis padded by ``pad`` after its end with symmetric
    reflection (``abcd|dcba|abcd...``, numpy's ``mode='symmetric'``), for any pad size."""
    i = torch.arange(n + pad, device=device) % (2 * n)
    return torch.where(i >= n, 2 * n - 1 - i, i)


def pad_to_multiple(x: torch.Tensor, multiple: int = 8) -> torch.Tensor:
    """Pad [B, C, H, W] at the bottom and right to multiples of ``multiple`` by symmetric reflection."""
    h, w = x.shape[-2:]
    ph, pw = (-h) % multiple, (-w) % multiple
    if ph:
        x = x.index_select(-2, symmetric_pad_index(h, ph, x.device))
    if pw:
        x = x.index_select(-1, symmetric_pad_index(w, pw, x.device))
    return x


class LamaInpainter:
    """LaMa (``big-lama``) as a TorchScript module: ``net(image [B,3,H,W] in [0,1], mask [B,1,H,W]
    in {0,1}) -> [B,3,H,W]``, the format of lama-cleaner's ``big-lama.pt``.

    Inputs are padded at the bottom/right to a multiple of 8 by symmetric reflection (LaMa's
    ``pad_img_to_modulo``), the output is cropped back, clamped to [0, 1], and pasted inside the
    mask only. ``batch`` views go through the network at a time.
    """

    name = "lama"

    def __init__(self, module: torch.jit.ScriptModule, device: Union[str, torch.device, None] = None,
                 batch: int = 1, path: Optional[Path] = None) -> None:
        self.net = module.eval()
        self.device = torch.device(device) if device is not None else None
        if self.device is not None:
            self.net = self.net.to(self.device)
        self.batch, self.path = max(int(batch), 1), path

    @classmethod
    def load(cls, path: Optional[PathLike] = None, *, models=None, device=None, batch: int = 1) -> "LamaInpainter":
        """Load ``big-lama.pt`` from ``path``, a model config, or ``$TIGER_MODELS/lama/``.

        Raises ModelNotFoundError (naming the file and the places looked at) when it is missing,
        and ValueError naming the file when it is not a loadable TorchScript module.
        """
        from tiger.models.paths import resolve_model_path

        file = resolve_model_path("lama", path, config=models)
        try:
            module = torch.jit.load(str(file), map_location=device or "cpu")
        except Exception as e:  # torch raises RuntimeError or ValueError, depending on the damage
            raise ValueError(f"tiger.delete.LamaInpainter: {file} is not a TorchScript module "
                             f"(expected lama-cleaner's big-lama.pt): {e}") from e
        log.info("LaMa inpainter loaded from %s", file)
        return cls(module, device=device, batch=batch, path=Path(file))

    @torch.no_grad()
    def __call__(self, images: torch.Tensor, masks: torch.Tensor) -> torch.Tensor:
        m = check_inpaint_inputs(images, masks, "LamaInpainter")
        dev = self.device or images.device
        h, w = images.shape[-2:]
        outs = []
        for s in range(0, images.shape[0], self.batch):
            img = pad_to_multiple(images[s:s + self.batch].to(dev, torch.float32))
            msk = pad_to_multiple(m[s:s + self.batch].to(dev, torch.float32))
            res = self.net(img, msk)
            if not isinstance(res, torch.Tensor) or tuple(res.shape) != tuple(img.shape):
                got = list(res.shape) if isinstance(res, torch.Tensor) else type(res).__name__
                raise ValueError(f"tiger.delete.LamaInpainter: the network returned {got}, expected "
                                 f"{list(img.shape)} (is {self.path} a big-lama TorchScript module?)")
            outs.append(res[..., :h, :w].clamp(0, 1).to(images.device))
        return paste(images, torch.cat(outs), m)


def make_inpainter(name: str = "opencv", *, path: Optional[PathLike] = None, models=None,
                   device=None, **kwargs) -> Inpainter:
    """An inpainter by name: ``"opencv"`` / ``"telea"`` (built in), ``"ns"`` (OpenCV Navier-Stokes)
    or ``"lama"`` (needs ``big-lama.pt``; see :meth:`LamaInpainter.load`)."""
    if name in ("opencv", "telea"):
        return OpenCVInpainter(method="telea", **kwargs)
    if name == "ns":
        return OpenCVInpainter(method="ns", **kwargs)
    if name == "lama":
        return LamaInpainter.load(path, models=models, device=device, **kwargs)
    raise ValueError(f"tiger.delete: unknown inpainter {name!r}; use 'opencv' (Telea), 'ns' or 'lama'")
