"""Pictures: PNG writing (atomic), depth colouring and PCA views of feature maps."""
from __future__ import annotations

import os
from pathlib import Path
from typing import Optional, Union

import numpy as np
import torch
from torch import Tensor

from .io import atomic_write
from .pca import fit_pca


def to_uint8(img: Union[Tensor, np.ndarray]) -> np.ndarray:
    """[H,W] or [H,W,3|4] float in [0,1] (or uint8) → uint8 array."""
    if isinstance(img, Tensor):
        img = img.detach().float().cpu().numpy()
    if img.dtype == np.uint8:
        return img
    return (np.clip(img, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)


def save_png(path: Union[str, os.PathLike], img: Union[Tensor, np.ndarray]) -> Path:
    """Write an image atomically as PNG. img: [H,W], [H,W,3] or [H,W,4], float [0,1] or uint8."""
    from PIL import Image

    path = Path(path)
    with atomic_write(path, "wb") as fh:
        Image.fromarray(to_uint8(img)).save(fh, format="PNG")
    return path


def colorize(values: Tensor, mask: Optional[Tensor] = None, cmap: str = "turbo",
             vmin: Optional[float] = None, vmax: Optional[float] = None) -> Tensor:
    """Map a scalar image [H,W] through a matplotlib colormap → [H,W,3] in [0,1].

    Pixels outside ``mask`` [H,W] bool are black; the range defaults to the masked 1st/99th
    percentiles so a few outliers do not wash the picture out.
    """
    import matplotlib

    v = values.detach().float().cpu()
    m = torch.ones_like(v, dtype=torch.bool) if mask is None else mask.detach().cpu()
    sel = v[m]
    if sel.numel() == 0:
        return torch.zeros(*v.shape, 3)
    lo = float(torch.quantile(sel, 0.01)) if vmin is None else vmin
    hi = float(torch.quantile(sel, 0.99)) if vmax is None else vmax
    t = ((v - lo) / max(hi - lo, 1e-12)).clamp(0, 1)
    rgb = torch.from_numpy(matplotlib.colormaps[cmap](t.numpy())[..., :3]).float()
    return rgb * m[..., None]


def feature_pca_image(features: Tensor, mask: Optional[Tensor] = None,
                      basis: Optional[Tensor] = None) -> Tensor:
    """Show a [H,W,D] feature map as RGB through its first 3 principal components.

    Components are fitted on the masked pixels (or taken from ``basis`` [D,3], so several
    views share colours) and each scaled to its 1st–99th percentile range → [H,W,3].
    """
    h, w, d = features.shape
    f = features.detach().float().cpu().reshape(-1, d)
    m = torch.ones(h * w, dtype=torch.bool) if mask is None else mask.detach().cpu().reshape(-1)
    if int(m.sum()) < 3:
        return torch.zeros(h, w, 3)
    if basis is None:
        basis = pca_basis(f[m], 3)
    proj = (f - f[m].mean(0)) @ basis
    lo = torch.quantile(proj[m], 0.01, dim=0)
    hi = torch.quantile(proj[m], 0.99, dim=0)
    rgb = ((proj - lo) / (hi - lo).clamp_min(1e-12)).clamp(0, 1)
    return (rgb * m[:, None]).reshape(h, w, 3)


def pca_basis(x: Tensor, k: int) -> Tensor:
    """Top-k principal directions [D,k] of rows x [M,D] (deterministic sign; the first 200k rows
    are enough for a picture)."""
    return fit_pca(x[:200_000], min(k, x.shape[1]))[1].to(device=x.device, dtype=x.dtype)


#: Colour-bar layout of :func:`with_colorbar`, in pixels.
BAR_GAP, BAR_WIDTH, BAR_LABEL_WIDTH = 4, 12, 52


def value_range(values: Tensor, mask: Optional[Tensor] = None) -> tuple[float, float]:
    """The masked 1st/99th percentiles of ``values`` [H, W] (the range :func:`colorize` uses);
    (0, 1) when the mask is empty."""
    v = values.detach().float().cpu()
    sel = v[mask.detach().cpu()] if mask is not None else v.reshape(-1)
    if sel.numel() == 0:
        return 0.0, 1.0
    return float(torch.quantile(sel, 0.01)), float(torch.quantile(sel, 0.99))


def with_colorbar(picture: Tensor, vmin: float, vmax: float, cmap: str = "turbo",
                  unit: str = "") -> Tensor:
    """``picture`` [H, W, 3] in [0, 1] with a vertical colour bar on its right: ``vmax`` at the top,
    ``vmin`` at the bottom, both written beside it (with ``unit``). Returns [H, W + 68, 3] on white."""
    from PIL import Image, ImageDraw

    h, w = int(picture.shape[0]), int(picture.shape[1])
    ramp = torch.linspace(vmax, vmin, h)[:, None].expand(h, BAR_WIDTH)
    bar = colorize(ramp, None, cmap, vmin, vmax)
    canvas = Image.new("RGB", (w + BAR_GAP + BAR_WIDTH + BAR_LABEL_WIDTH, h), (255, 255, 255))
    canvas.paste(Image.fromarray(to_uint8(picture[..., :3])), (0, 0))
    canvas.paste(Image.fromarray(to_uint8(bar)), (w + BAR_GAP, 0))
    draw = ImageDraw.Draw(canvas)
    x = w + BAR_GAP + BAR_WIDTH + 2
    draw.text((x, 0), f"{vmax:.3g}{unit}", fill=(0, 0, 0))
    draw.text((x, max(h - 11, 10)), f"{vmin:.3g}{unit}", fill=(0, 0, 0))
    return torch.from_numpy(np.array(canvas)).float() / 255


def depth_picture(depth: Tensor, mask: Optional[Tensor] = None, cmap: str = "turbo") -> Tensor:
    """A depth map [H, W] coloured over its masked 1st-99th percentile range, with the colour bar
    naming that range in scene units (near at the bottom). Pixels outside ``mask`` are black."""
    lo, hi = value_range(depth, mask)
    return with_colorbar(colorize(depth, mask, cmap, lo, hi), lo, hi, cmap)
