"""The one interface between the edit loop and a guidance (score distillation or analytic).

A guidance receives the current renders of V views and returns ``dL/drenders``: the gradient the
edit loop back-propagates through the rasterizer (``renders.backward(grad)``). It never sees the
scene, so any model (InstructPix2Pix, MVDream, the analytic ideal denoiser, ``recolor``) plugs in.
"""
from __future__ import annotations

import math

from dataclasses import dataclass, field
from typing import Optional, Protocol, Sequence, runtime_checkable

import torch

from tiger.scene.cameras import Camera


@dataclass
class ViewBatch:
    """What a guidance may know about the V views of one edit step.

    Attributes:
        cameras: the V cameras the renders were made from (OpenCV world-to-camera).
        originals: [V, 3, H, W] renders of the *unedited* scene from the same cameras, in [0, 1]
            (InstructPix2Pix's image condition; ``recolor``'s shading reference).
        masks: [V, 1, H, W] rendered relevance / object mask in [0, 1] (the edited object's
            footprint), or None.
        view_ids: optional [V] integer ids of the cameras in a pre-sampled pool, so a guidance
            can cache per-camera work (e.g. the image-condition latents) across steps.
        step: the edit step (0-based) and ``total_steps``; schedules read them.
        object_center: [3] world position of the edited object's centre (MVDream's camera frame).
        world_up: [3] the scene's up direction (MVDream's z axis); None: estimated from the cameras.
    """

    cameras: Sequence[Camera]
    originals: torch.Tensor
    masks: Optional[torch.Tensor] = None
    view_ids: Optional[torch.Tensor] = None
    step: int = 0
    total_steps: int = 1
    object_center: Optional[torch.Tensor] = None
    world_up: Optional[torch.Tensor] = None


@dataclass
class GuidanceInfo:
    """Diagnostics of one guidance call (logged, never used for the gradient)."""

    loss: float = 0.0
    t: Optional[torch.Tensor] = None
    timings_ms: dict[str, float] = field(default_factory=dict)
    extra: dict[str, float] = field(default_factory=dict)


@runtime_checkable
class Guidance(Protocol):
    """A source of gradients on rendered views.

    ``grad(renders, views)`` takes renders [V, 3, H, W] in [0, 1] (any float dtype, any device,
    not requiring grad) and returns ``(g, info)`` with ``g`` of the same shape: the gradient of
    the guidance's loss with respect to the renders. Implementations must return finite values
    (non-finite entries zeroed) and raise ``ValueError`` naming the tensor on bad input.
    """

    name: str

    def grad(self, renders: torch.Tensor, views: ViewBatch) -> tuple[torch.Tensor, GuidanceInfo]:
        ...


def check_renders(renders: torch.Tensor, who: str, views: Optional[int] = None) -> None:
    """Raise a clear ``ValueError`` unless ``renders`` is a finite [V, 3, H, W] batch in [0, 1]
    (:func:`check_render_shape`, then :func:`check_render_values`).

    Args:
        renders: the tensor to check.
        who: the guidance's name, used in the message.
        views: the exact number of views required (e.g. 4 for MVDream), or None for any.
    """
    check_render_shape(renders, who, views)
    check_render_values(renders, who)


def check_render_shape(renders: torch.Tensor, who: str, views: Optional[int] = None) -> None:
    """The checks of :func:`check_renders` that need no values (no host synchronisation)."""
    if not isinstance(renders, torch.Tensor) or renders.ndim != 4 or renders.shape[1] != 3:
        shape = list(renders.shape) if isinstance(renders, torch.Tensor) else type(renders).__name__
        raise ValueError(f"tiger.edit.{who}: renders must be [V, 3, H, W], got {shape}")
    if views is not None and renders.shape[0] != views:
        raise ValueError(f"tiger.edit.{who}: needs exactly {views} views, got renders with V={renders.shape[0]}")
    if not renders.is_floating_point():
        raise ValueError(f"tiger.edit.{who}: renders must be a float tensor, got {renders.dtype}")


def check_render_values(renders: torch.Tensor, who: str) -> None:
    """Finite and in [0, 1], with one read-back (a guidance calls it after queueing its other
    inputs, just before its step, so the GPU waits only for the step's launch)."""
    lo_t, hi_t = torch.aminmax(renders)
    lo, hi = torch.stack([lo_t, hi_t]).float().tolist()  # NaN propagates to both
    if not (math.isfinite(lo) and math.isfinite(hi)):
        raise ValueError(f"tiger.edit.{who}: renders contain NaN or Inf")
    if lo < -1e-3 or hi > 1 + 1e-3:
        raise ValueError(f"tiger.edit.{who}: renders must lie in [0, 1], got values in [{lo:.4g}, {hi:.4g}]")
