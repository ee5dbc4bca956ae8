"""2D relevancy maps: render each Gaussian's L, score every pixel, draw heat-maps over the image."""
from __future__ import annotations

import logging
import os
from pathlib import Path
from typing import Optional, Sequence, Union

import numpy as np
import torch

from tiger.render import Camera
from tiger.scene import GaussianScene, render_rgb
from tiger.scene.gaussian_scene import RasterOption
from tiger.utils.io import atomic_write, file_slug

from .relevance import DEFAULT_TEMPERATURE, relevancy
from .text import CANONICAL_NEGATIVES, PCASource, Query, TextEncoder, embed_negatives, embed_queries

log = logging.getLogger(__name__)
PathLike = Union[str, os.PathLike]


def render_language(scene: GaussianScene, camera: Camera,
                    **options: RasterOption) -> tuple[torch.Tensor, torch.Tensor]:
    """Render the language features: ([H, W, D] features, [H, W] alpha); background 0, no grad."""
    if scene.lang is None:
        raise ValueError("tiger.retrieval: the scene has no language features to render (scene.lang)")
    with torch.no_grad():
        out = scene.render(camera, "lang", **options)
    return out["color"], out["alpha"]


def relevancy_maps(scene: GaussianScene, camera: Camera, queries: torch.Tensor, negatives: Optional[torch.Tensor] = None,
                   *, temperature: float = DEFAULT_TEMPERATURE) -> dict[str, Optional[torch.Tensor]]:
    """Per-pixel cosine and LERF relevancy of the rendered language features.

    Args:
        queries: [Q, D] query embeddings in the language space (:func:`embed_queries`).
        negatives: [M, D] canonical negatives (None: cosine only).
    Returns:
        dict with 'cosine' [Q, H, W], 'relevancy' [Q, H, W] or None, 'alpha' [H, W], 'features' [H, W, D].
    """
    feats, alpha = render_language(scene, camera)
    cos, rel = relevancy(feats, queries, negatives, temperature=temperature)
    return {"cosine": cos.permute(2, 0, 1), "relevancy": None if rel is None else rel.permute(2, 0, 1),
            "alpha": alpha, "features": feats}


def _to_numpy(x: Optional[torch.Tensor]) -> Optional[np.ndarray]:
    return None if x is None else x.detach().float().cpu().numpy()


def save_heatmap(path: PathLike, values: torch.Tensor, image: Optional[torch.Tensor] = None, *,
                 title: str = "", cmap: str = "turbo", vmin: Optional[float] = None,
                 vmax: Optional[float] = None, alpha: float = 0.6, below: Optional[float] = None,
                 boxes: Optional[Sequence[Sequence[float]]] = None,
                 points: Optional[Sequence[Sequence[float]]] = None, label: str = "relevancy",
                 dpi: int = 100) -> Path:
    """Write a heat-map of ``values`` [H, W] over ``image`` [H, W, 3] (in [0, 1]) with a colour bar.

    Args:
        below: pixels with values under this are left uncoloured (LERF shows relevancy > 0.5 only).
        boxes: [x1, y1, x2, y2] pixel boxes drawn as rectangles (ground truth).
        points: (x, y) pixel positions marked (predictions).
    The file (PNG, or any format matplotlib knows from the suffix) is written atomically.
    """
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure
    from matplotlib.patches import Rectangle

    v = _to_numpy(values)
    if v is None or v.ndim != 2:
        raise ValueError(f"tiger.retrieval: heat-map values must be [H, W], got {None if v is None else v.shape}")
    h, w = v.shape
    img = _to_numpy(image)
    if img is not None and img.shape[:2] != (h, w):
        raise ValueError(f"tiger.retrieval: image {img.shape} does not match the heat-map size {(h, w)}")
    # Sized so the image is drawn at about its native resolution (plus room for the colour bar).
    fig = Figure(figsize=(max(4.0, 1.1 * w / dpi) + 1.5, max(3.0, 1.1 * h / dpi) + 0.6), dpi=dpi)
    FigureCanvasAgg(fig)
    ax = fig.add_subplot(1, 1, 1)
    if img is not None:
        ax.imshow(np.clip(img[..., :3], 0, 1), interpolation="nearest")
    shown = np.ma.masked_where(v < below, v) if below is not None else v
    im = ax.imshow(shown, cmap=cmap, vmin=vmin, vmax=vmax, alpha=alpha if img is not None else 1.0,
                   interpolation="nearest")
    fig.colorbar(im, ax=ax, fraction=0.046, pad=0.04, label=label)
    for b in boxes or []:
        x1, y1, x2, y2 = (float(c) for c in b)
        ax.add_patch(Rectangle((min(x1, x2), min(y1, y2)), abs(x2 - x1), abs(y2 - y1), fill=False,
                               edgecolor="black", linewidth=2, linestyle="--"))
    if points is not None and len(points):
        pts = np.asarray(points, dtype=np.float64).reshape(-1, 2)
        ax.scatter(pts[:, 0], pts[:, 1], s=60, c="red", edgecolors="black", linewidths=1.5, zorder=3)
    ax.set_xlim(-0.5, w - 0.5)
    ax.set_ylim(h - 0.5, -0.5)
    ax.set_axis_off()
    if title:
        ax.set_title(title)
    path = Path(path)
    fmt = path.suffix.lstrip(".").lower() or "png"
    with atomic_write(path, "wb") as fh:
        fig.savefig(fh, format=fmt, bbox_inches="tight")
    return path


# Layout of :func:`save_relevancy_picture` (pixels): a title strip, then the panels side by side.
TITLE_H, GAP, BAR_W, LABEL_W = 14, 6, 12, 40
EMPTY = (0, 0, 0)  # heat-panel pixels with no Gaussian behind them


def save_relevancy_picture(path: PathLike, values: torch.Tensor, alpha: torch.Tensor,
                           image: Optional[torch.Tensor] = None, *, vmin: float, vmax: float,
                           title: str = "", cmap: str = "turbo") -> Path:
    """One view's relevancy as ``[render | heat map | colour bar]`` at the view's resolution.

    The heat map is drawn alone (not blended over the render, whose colours would shift it:
    a red high over a blue object reads purple), so the colour bar reads directly; pixels
    where ``alpha`` [H, W] < 0.5 (no Gaussian) are black instead of the colour of the score
    of empty space. ``values`` [H, W] are clipped to [vmin, vmax]; ``image`` [H, W, 3] in
    [0, 1] is the render shown on the left (omitted when None). Panels start ``TITLE_H``
    pixels from the top, ``GAP`` apart. Written atomically as PNG.
    """
    from PIL import Image, ImageDraw

    from tiger.utils.images import colorize, to_uint8

    h, w = values.shape
    if alpha.shape != (h, w) or (image is not None and tuple(image.shape[:2]) != (h, w)):
        raise ValueError(f"tiger.retrieval: relevancy picture: values {tuple(values.shape)}, alpha "
                         f"{tuple(alpha.shape)} and image {None if image is None else tuple(image.shape)} "
                         "must share H and W")
    heat = colorize(values, alpha.detach().cpu() >= 0.5, cmap, vmin, vmax)
    bar_values = torch.linspace(vmax, vmin, h)[:, None].expand(h, BAR_W)
    bar = colorize(bar_values, None, cmap, vmin, vmax)
    panels = ([image.detach().float().cpu()[..., :3].clamp(0, 1)] if image is not None else []) + [heat]
    x_bar = len(panels) * (w + GAP)
    canvas = Image.new("RGB", (x_bar + BAR_W + LABEL_W, TITLE_H + h), (255, 255, 255))
    for k, panel in enumerate(panels):
        canvas.paste(Image.fromarray(to_uint8(panel)), (k * (w + GAP), TITLE_H))
    canvas.paste(Image.fromarray(to_uint8(bar)), (x_bar, TITLE_H))
    draw = ImageDraw.Draw(canvas)
    draw.text((2, 1), title, fill=(0, 0, 0))
    draw.text((x_bar + BAR_W + 3, TITLE_H), f"{vmax:g}", fill=(0, 0, 0))
    draw.text((x_bar + BAR_W + 3, TITLE_H + h - 11), f"{vmin:g}", fill=(0, 0, 0))
    path = Path(path)
    with atomic_write(path, "wb") as fh:
        canvas.save(fh, format="PNG")
    return path


def write_relevancy_pictures(scene: GaussianScene, cameras: Sequence[Camera], query: Query,
                             out_dir: PathLike, *, encoder: Optional[TextEncoder] = None,
                             pca: PCASource = None,
                             negatives: Union[None, Sequence[str], torch.Tensor] = CANONICAL_NEGATIVES,
                             score: str = "relevancy", temperature: float = DEFAULT_TEMPERATURE,
                             names: Optional[Sequence[str]] = None) -> list[Path]:
    """Pictures of one query for the given views: ``out_dir/<query>_<view>.png``, each the render
    beside the heat map alone (:func:`save_relevancy_picture`).

    ``score="relevancy"`` maps the LERF relevancy over [0.5, 1] (lower values at the low end, as
    LERF shows only > 0.5); ``"cosine"`` the cosine over [-1, 1].
    """
    if score not in ("cosine", "relevancy"):
        raise ValueError(f"tiger.retrieval: score must be 'cosine' or 'relevancy', got '{score}'")
    d = scene.lang.shape[1]
    pca_src = scene if pca is None else pca
    q = embed_queries(query, dim=d, encoder=encoder, pca=pca_src)
    neg = None
    if score == "relevancy":
        if negatives is None or (encoder is None and not torch.is_tensor(negatives)):
            raise ValueError("tiger.retrieval: relevancy pictures need negatives (embeddings, or strings "
                             "with a text encoder)")
        neg = embed_negatives(negatives, dim=d, encoder=encoder, pca=pca_src)
    text = query if isinstance(query, str) else "query"
    out_dir = Path(out_dir)
    paths = []
    for i, cam in enumerate(cameras):
        view = names[i] if names is not None else (cam.image_name or f"view{i:03d}")
        maps = relevancy_maps(scene, cam, q[:1], neg, temperature=temperature)
        vals = maps["relevancy"][0] if score == "relevancy" else maps["cosine"][0]
        vmin, vmax = (0.5, 1.0) if score == "relevancy" else (-1.0, 1.0)
        p = out_dir / f"{file_slug(text)}_{file_slug(Path(view).stem)}.png"
        save_relevancy_picture(p, vals, maps["alpha"], render_rgb(scene, [cam])[0], vmin=vmin, vmax=vmax,
                               title=f"'{text}' ({score})")
        paths.append(p)
    log.info("wrote %d relevancy pictures to %s", len(paths), out_dir)
    return paths
