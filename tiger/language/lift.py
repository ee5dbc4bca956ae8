"""Training-free lifting of 2D feature maps onto Gaussians (Occam's LGS-style).

Each Gaussian's embedding is the weighted mean of the feature maps over the pixels it contributes
to, the weight of pixel p being its blending weight w_ip = T_i(p) alpha_i(p) there:

    L_i = sum_v sum_p w_ip F_v(p) / sum_v sum_p w_ip        (valid pixels only)

One pass over the views. Both sums are the gradient of ``sum_p <render(c)(p), G(p)>`` with respect
to the per-Gaussian channels c (the rasterizer is linear in c with coefficients w_ip): with
G = [F * valid, valid] the rasterizer's features-only backward returns numerator and denominator
in one call, with alphas that are exactly the forward's. No separate kernel, so no second copy
of the tile walk to keep in step with the renderer.
"""
from __future__ import annotations

import logging
import time
from dataclasses import dataclass
from typing import Callable, Optional, Sequence

import torch

from tiger.render import Camera
from tiger.scene import GaussianScene

from .feature_maps import FeatureSource, ResidentMaps, as_map, map_loader
from .frozen_views import FrozenViews

log = logging.getLogger(__name__)


@dataclass
class LiftResult:
    """Outcome of :func:`lift`.

    Attributes:
        lang: [N, D] the lifted embeddings (0 where ``weight`` is 0).
        weight: [N] float64 sum of the Gaussian's blending weights over the valid pixels of all views.
        seconds: wall time.
    """

    lang: torch.Tensor
    weight: torch.Tensor
    seconds: float

    def coverage(self) -> str:
        """One line on the Gaussians that reached no valid pixel."""
        silent = int((self.weight <= 0).sum())
        return f"{silent} of {self.lang.shape[0]} Gaussians reach no valid pixel in any view (L = 0)"


def _lift_view(color_of: Callable[[torch.Tensor], torch.Tensor], feats: torch.Tensor,
               valid: Optional[torch.Tensor], n: int, dtype: torch.dtype,
               device: torch.device) -> tuple[torch.Tensor, torch.Tensor]:
    """One view's (numerator [N, D], denominator [N]) in float64: the gradient of
    sum_p <color_of(c)(p), [F * valid, valid](p)> with respect to c [N, D + 1].

    ``color_of(channels [N, C]) -> [H, W, C]`` renders the view at the map's size."""
    h, w, d = (int(s) for s in feats.shape)
    weight = (torch.ones(h, w, 1, dtype=dtype, device=device) if valid is None
              else valid.to(device=device, dtype=dtype).unsqueeze(-1))
    g_out = torch.cat([feats.to(device=device, dtype=dtype) * weight, weight], dim=-1)
    channels = torch.zeros(n, d + 1, dtype=dtype, device=device, requires_grad=True)
    with torch.enable_grad():
        (grad,) = torch.autograd.grad(color_of(channels), channels, g_out)
    return grad[:, :d].double(), grad[:, d].double()


def _result(num: torch.Tensor, den: torch.Tensor, dtype: torch.dtype, t0: float) -> LiftResult:
    lang = torch.where(den[:, None] > 0, num / den.clamp_min(1e-300)[:, None], torch.zeros_like(num))
    return LiftResult(lang=lang.to(dtype), weight=den, seconds=time.perf_counter() - t0)


def lift(scene: GaussianScene, cameras: Sequence[Camera], feature_maps: FeatureSource, *,
         progress: bool = False) -> LiftResult:
    """Lift per-view feature maps onto the Gaussians of ``scene`` (geometry untouched).

    Args:
        scene: the Gaussians ([N]); only their geometry and opacity are used.
        cameras: V views; each is rendered at its feature map's size (K rescaled).
        feature_maps: per view ``[H, W, D]``, ``(features, valid [H, W] bool)`` or a dict, as a
            sequence, a callable ``i -> map`` or a ``tiger.language.FeatureSet`` (see
            :func:`tiger.language.field.train_field`).
        progress: show a tqdm bar over the views.
    Returns:
        :class:`LiftResult` with ``lang`` [N, D] in the scene's dtype and device.
    """
    cameras = list(cameras)
    if not cameras:
        raise ValueError("tiger.lift: no cameras given")
    load = map_loader(feature_maps, cameras)
    frozen = scene.detach()
    frozen.lang = None
    n, device, dtype = len(frozen), frozen.device, frozen.dtype
    num: torch.Tensor | None = None
    den = torch.zeros(n, dtype=torch.float64, device=device)
    t0 = time.perf_counter()
    from tiger.utils.progress import progress as progress_lines

    for v in progress_lines(range(len(cameras)), "lifting", unit="view", disable=not progress):
        feats, valid = as_map(load(v), v)
        h, w, d = (int(s) for s in feats.shape)
        if num is None:
            num = torch.zeros(n, d, dtype=torch.float64, device=device)
        elif d != num.shape[1]:
            raise ValueError(f"tiger.lift: feature map {v} has {d} channels, map 0 has {num.shape[1]}")
        cam = cameras[v].resized(w, h)
        part_num, part_den = _lift_view(lambda c: frozen.render(cam, c, check_finite=False)["color"],
                                        feats, valid, n, dtype, device)
        num += part_num
        den += part_den
    assert num is not None
    return _result(num, den, dtype, t0)


def lift_views(views: FrozenViews, maps: ResidentMaps, *, progress: bool = False) -> LiftResult:
    """:func:`lift` from views whose projections and tile lists are kept (the ones the field's
    training then renders) and maps already read (each view is rendered at its map's size)."""
    device, dtype = views.cameras[0].viewmat.device, views.cameras[0].viewmat.dtype
    n, d = views.count, maps.dim
    num = torch.zeros(n, d, dtype=torch.float64, device=device)
    den = torch.zeros(n, dtype=torch.float64, device=device)
    t0 = time.perf_counter()
    from tiger.utils.progress import progress as progress_lines

    for v in progress_lines(range(len(views)), "lifting", unit="view", disable=not progress):
        m = maps.get(v)
        maps.prefetch([v + 1] if v + 1 < len(views) else [])  # streamed maps: the next one while this renders
        part_num, part_den = _lift_view(lambda c: views.render(v, c)[0], m.features, m.valid, n, dtype, device)
        num += part_num
        den += part_den
    return _result(num, den, dtype, t0)


def lift_features(scene: GaussianScene, cameras: Sequence[Camera], feature_maps: FeatureSource, *,
                  progress: bool = False) -> torch.Tensor:
    """[N, D] per-Gaussian weighted means of the feature maps (see :func:`lift`)."""
    return lift(scene, cameras, feature_maps, progress=progress).lang
