"""The one interface between the edit loop and a guidance (score distillation or analytic).

A guidance receives the current renders of V views and returns ``dL/drenders``: the gradient the
edit loop back-propagates through the rasterizer (``renders.backward(grad)``). It never sees the
scene, so any model (InstructPix2Pix, MVDream, the analytic ideal denoiser, ``recolor``) plugs in.
"""
from __future__ import annotations

import math

from dataclasses import dataclass, field
from typing import Any, Optional, Protocol, Sequence, runtime_checkable

import torch

from tiger.render import Camera


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
    """A source of gradients on rendered views: everything the edit loop and ``tiger edit`` use.

    - ``name``: the guidance's kind (``"recolor"``, ``"ip2p"``, ``"csd"``, ...), recorded.
    - ``instruction``: the edit text the guidance follows (the one place it is given; the edit
      records it from here).
    - ``grad(renders, views)`` takes renders [V, 3, H, W] in [0, 1] (any float dtype, any device,
      not requiring grad) and returns ``(g, info)`` with ``g`` of the same shape: the gradient of
      the guidance's loss with respect to the renders. Implementations must return finite values
      (non-finite entries zeroed) and raise ``ValueError`` naming the tensor on bad input.
    - ``settings()``: a JSON-serialisable dict of everything that decides the gradients besides
      the instruction (schedule, model dtype, CUDA-graph use, noise range, ...), as it runs. The
      edit writes it to its record (``edit.json``) and its checkpoint signature, so a record is
      the settings that ran and a resume with other settings is refused. It must not change
      while the guidance is used (a lazily loaded model reports the dtype it will load with).
    - ``generators()``: every ``torch.Generator`` the guidance draws from, in a fixed order,
      without repeats (empty for a deterministic one); the edit loop checkpoints and restores
      their states, so a resumed edit draws the same noise.
    - ``reset_caches()``: forget work cached across steps (e.g. InstructPix2Pix's image-condition
      latents keyed by camera id); the edit loop calls it when a round starts, since pool ids of
      an earlier round name other cameras.

    Optional: ``prepare(views)`` caches, ahead of the step that uses ``views``, the work that
    depends only on its cameras and original renders (InstructPix2Pix's image-condition latents
    and MVDream's camera conditions of pooled views); it returns the tensors it made, so that a
    caller running it on another CUDA stream can hand them to its own (:func:`prepare_guidance`).
    The edit loop calls it for the next step's pool set beside the current step.

    :func:`check_guidance` checks an object against this list with a message naming what is missing.
    """

    name: str
    instruction: str

    def grad(self, renders: torch.Tensor, views: ViewBatch) -> tuple[torch.Tensor, GuidanceInfo]:
        ...

    def settings(self) -> dict[str, Any]:
        ...

    def generators(self) -> list[torch.Generator]:
        ...

    def reset_caches(self) -> None:
        ...


#: The protocol's members: (attribute, whether it is a method).
PROTOCOL_MEMBERS = (("name", False), ("instruction", False), ("grad", True), ("settings", True),
                    ("generators", True), ("reset_caches", True))


def check_guidance(guidance: object) -> Guidance:
    """``guidance`` itself when it has every member of :class:`Guidance`, else a ``TypeError``
    naming the missing ones (a string ``name``/``instruction`` and callable methods)."""
    missing = []
    for member, is_method in PROTOCOL_MEMBERS:
        value = getattr(guidance, member, None)
        if is_method and not callable(value):
            missing.append(f"{member}()")
        elif not is_method and not isinstance(value, str):
            missing.append(f"{member} (a string)")
    if missing:
        raise TypeError(f"tiger.edit: guidance {type(guidance).__name__} lacks {', '.join(missing)} of the "
                        "Guidance protocol (tiger.edit.guidance.base.Guidance: name, instruction, grad, settings, "
                        "generators, reset_caches)")
    return guidance  # type: ignore[return-value]


def prepare_guidance(guidance: Guidance, views: ViewBatch) -> list[torch.Tensor]:
    """``guidance.prepare(views)`` (the protocol's optional member) as a list of the tensors it
    cached; ``[]`` for a guidance without one."""
    fn = getattr(guidance, "prepare", None)
    return list(fn(views)) if callable(fn) else []


def unique_generators(*groups: Sequence[torch.Generator]) -> list[torch.Generator]:
    """The generators of several guidances in order, each once (two parts may share one)."""
    out: list[torch.Generator] = []
    for group in groups:
        out.extend(g for g in group if all(g is not o for o in out))
    return out


def dtype_name(dtype: Optional[torch.dtype]) -> Optional[str]:
    """``torch.bfloat16`` -> ``"bfloat16"`` (settings records), None stays None."""
    return None if dtype is None else str(dtype).removeprefix("torch.")


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
