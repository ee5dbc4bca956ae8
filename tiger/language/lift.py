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
from typing import Sequence

import torch

from tiger.render import Camera
from tiger.scene import GaussianScene

from .feature_maps import FeatureSource, as_map, map_loader

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
        weight = (torch.ones(h, w, 1, dtype=dtype, device=device) if valid is None
                  else valid.to(device=device, dtype=dtype).unsqueeze(-1))
        g_out = torch.cat([feats.to(device=device, dtype=dtype) * weight, weight], dim=-1)
        channels = torch.zeros(n, d + 1, dtype=dtype, device=device, requires_grad=True)
        with torch.enable_grad():
            out = frozen.render(cameras[v].resized(w, h), channels, check_finite=False)
            (grad,) = torch.autograd.grad(out["color"], channels, g_out)
        num += grad[:, :d].double()
        den += grad[:, d].double()
    assert num is not None
    lang = torch.where(den[:, None] > 0, num / den.clamp_min(1e-300)[:, None], torch.zeros_like(num))
    return LiftResult(lang=lang.to(dtype), weight=den, seconds=time.perf_counter() - t0)


def lift_features(scene: GaussianScene, cameras: Sequence[Camera], feature_maps: FeatureSource, *,
                  progress: bool = False) -> torch.Tensor:
    """[N, D] per-Gaussian weighted means of the feature maps (see :func:`lift`)."""
    return lift(scene, cameras, feature_maps, progress=progress).lang
