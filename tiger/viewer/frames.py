"""One viewer frame: render the scene at a camera in a view mode and turn it into 8-bit RGB.

The per-frame path stays short: one rasterizer call (3 channels for RGB, tint, depth, alpha and
feature PCA; the 64 language channels only for the relevancy heat map), the [0, 1] -> uint8
conversion on the scene's device, and one copy of the uint8 image to the host (none on the CPU:
``numpy()`` shares the tensor's memory). JPEG encoding happens where the frame is sent.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import numpy as np
import torch

from tiger.render import Camera
from tiger.scene import GaussianScene

MODES = ("RGB", "depth", "alpha", "language features", "relevancy")


@dataclass
class FrameInputs:
    """What a frame is drawn from (a consistent snapshot taken under the viewer's lock).

    Attributes:
        scene: the scene to draw (the selection alone when the viewer shows it alone).
        colors: [N, 3] per-Gaussian colours replacing the SH colour (highlight tint, feature PCA),
            or None for the SH colour.
        queries: [Q, D] unit query vectors for the relevancy heat map (None: no query).
        background: [3] RGB in [0, 1].
        mode: one of :data:`MODES`.
    """

    scene: GaussianScene
    colors: Optional[torch.Tensor]
    queries: Optional[torch.Tensor]
    background: tuple[float, float, float]
    mode: str = "RGB"


_LUT: dict[str, torch.Tensor] = {}


def colormap_lut(name: str = "turbo") -> torch.Tensor:
    """[256, 3] uint8 lookup table of a matplotlib colormap (built once)."""
    if name not in _LUT:
        import matplotlib

        rgb = matplotlib.colormaps[name](np.linspace(0.0, 1.0, 256))[:, :3]
        _LUT[name] = torch.from_numpy((rgb * 255.0 + 0.5).astype(np.uint8))
    return _LUT[name]


def _to_uint8(rgb: torch.Tensor) -> np.ndarray:
    """[H, W, 3] float in [0, 1] -> contiguous uint8 numpy (on the host)."""
    return rgb.clamp(0, 1).mul(255.0).add_(0.5).to(torch.uint8).cpu().numpy()


def _heat(values: torch.Tensor, valid: torch.Tensor, lo: float, hi: float,
          background: torch.Tensor) -> np.ndarray:
    """Scalar image [H, W] -> turbo colours (uint8 [H, W, 3]); invalid pixels get the background."""
    lut = colormap_lut("turbo").to(values.device)
    idx = ((values - lo) / max(hi - lo, 1e-12) * 255.0).clamp(0, 255).to(torch.long)
    out = lut[idx]
    bg = (background.clamp(0, 1) * 255.0 + 0.5).to(torch.uint8).to(values.device)
    out = torch.where(valid[..., None], out, bg)
    return out.cpu().numpy()


def draw_colour_bar(img: np.ndarray, lo: float, hi: float, label: str) -> np.ndarray:
    """Draw a vertical turbo colour bar with its range on the right edge of ``img`` (in place)."""
    import cv2

    h, w = img.shape[:2]
    bar_h, bar_w = max(int(h * 0.6), 20), max(w // 60, 8)
    x0, y0 = w - bar_w - 10, (h - bar_h) // 2
    if x0 < 0 or y0 < 12:
        return img
    lut = colormap_lut("turbo").numpy()
    ramp = lut[np.linspace(255, 0, bar_h).astype(np.int64)]
    img[y0:y0 + bar_h, x0:x0 + bar_w] = ramp[:, None, :]
    scale = max(0.35, h / 1400.0)
    for text, y in ((f"{hi:.2f}", y0 - 4), (f"{lo:.2f}", y0 + bar_h + int(14 * scale / 0.35))):
        cv2.putText(img, text, (max(x0 - 10, 0), y), cv2.FONT_HERSHEY_SIMPLEX, scale, (255, 255, 255), 1,
                    cv2.LINE_AA)
    cv2.putText(img, label, (max(x0 - 10, 0), y0 + bar_h + int(30 * scale / 0.35)), cv2.FONT_HERSHEY_SIMPLEX,
                scale, (255, 255, 255), 1, cv2.LINE_AA)
    return img


@torch.no_grad()
def render_frame(inputs: FrameInputs, camera: Camera) -> np.ndarray:
    """Draw ``inputs`` at ``camera``: uint8 [H, W, 3] RGB on the host (H, W: the camera's size)."""
    scene = inputs.scene
    dev = scene.device
    bg = torch.tensor(inputs.background, dtype=scene.dtype, device=dev)
    if len(scene) == 0:
        return np.broadcast_to(_to_uint8(bg)[None, None], (camera.height, camera.width, 3)).copy()
    mode = inputs.mode
    if mode == "relevancy":
        return _relevancy_frame(inputs, camera, bg)
    colors = inputs.colors
    if mode in ("RGB", "language features"):
        out = scene.render(camera, colors, background=bg, check_finite=False)
        return _to_uint8(out["color"])
    out = scene.render(camera, scene.means.new_zeros((len(scene), 1)), check_finite=False)
    alpha = out["alpha"]
    if mode == "alpha":
        return _to_uint8(alpha[..., None].expand(-1, -1, 3))
    if mode == "depth":
        valid = alpha > 0.5
        depth = out["depth"]
        d = depth[valid]
        lo, hi = (float(d.min()), float(d.max())) if d.numel() else (0.0, 1.0)
        img = _heat(depth, valid, lo, hi, bg)
        return draw_colour_bar(img, lo, hi, "depth")
    raise ValueError(f"tiger.viewer: unknown view mode {mode!r} (one of {', '.join(MODES)})")


def _relevancy_frame(inputs: FrameInputs, camera: Camera, bg: torch.Tensor) -> np.ndarray:
    """Cosine of the rendered language feature with the best of the queries, as a heat map."""
    from tiger.retrieval.relevance import relevancy

    scene = inputs.scene
    if scene.lang is None or inputs.queries is None:
        return render_frame(FrameInputs(scene, None, None, inputs.background, "RGB"), camera)
    out = scene.render(camera, "lang", check_finite=False)
    cos, _ = relevancy(out["color"], inputs.queries.to(scene.device), None, check_finite=False)
    best = cos.max(dim=-1).values
    valid = out["alpha"] > 0.5
    v = best[valid]
    lo, hi = (float(v.min()), float(v.max())) if v.numel() else (0.0, 1.0)
    img = _heat(best, valid, lo, hi, bg)
    return draw_colour_bar(img, lo, hi, "cosine")
