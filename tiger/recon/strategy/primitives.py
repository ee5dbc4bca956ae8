"""Densification primitives: row operations on a :class:`SceneOptimizer` that keep Adam's
moments aligned with the Gaussians (gsplat's ``strategy/ops.py`` split).

Each takes a [N] bool ``mask`` over the current Gaussians and an optional ``state`` dict of
other [N, ...] tensors (a rule's statistics) that follows the rows. Children inherit every
per-Gaussian attribute of their parent (``lang`` and the optimizer's ``extras`` included)
and start with zero Adam moments; removed Gaussians lose theirs.
"""
from __future__ import annotations

from typing import Optional

import torch

from tiger.scene.cameras import quat_to_rotmat
from tiger.scene.gaussian_scene import inverse_sigmoid

from ..step import SceneOptimizer

#: INRIA's split: two children whose scales are the parent's / (0.8 * 2).
SPLIT_CHILDREN = 2
SPLIT_SCALE_DIVISOR = 0.8 * SPLIT_CHILDREN


def _mask(opt: SceneOptimizer, mask: torch.Tensor, what: str) -> torch.Tensor:
    n = len(opt.scene)
    if not isinstance(mask, torch.Tensor) or mask.dtype != torch.bool or mask.shape != (n,):
        got = f"{mask.dtype} {list(mask.shape)}" if isinstance(mask, torch.Tensor) else type(mask).__name__
        raise ValueError(f"tiger.recon: {what} mask must be [N={n}] bool, got {got}")
    return mask.to(opt.scene.device)


def duplicate(opt: SceneOptimizer, mask: torch.Tensor, state: Optional[dict[str, torch.Tensor]] = None) -> int:
    """Append an identical copy of each Gaussian in ``mask`` (INRIA's clone); returns the count."""
    parents = torch.nonzero(_mask(opt, mask, "duplicate")).reshape(-1)
    if parents.numel():  # none: no row surgery (it would copy every tensor and Adam row unchanged)
        opt.edit_rows(parents=parents, state=state)
    return int(parents.numel())


def _split_children(opt: SceneOptimizer, idx: torch.Tensor,
                    generator: Optional[torch.Generator]) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
    """(parent of each child [2K], their ``means`` and ``log_scales`` [2K, 3]) of splitting rows
    ``idx`` [K]: positions drawn from the parent's Gaussian, scales divided by 1.6."""
    s = opt.scene
    rep = idx.repeat(SPLIT_CHILDREN)
    std = s.scales.detach()[rep]
    samples = torch.randn(std.shape, generator=generator, dtype=std.dtype).to(std.device) * std
    rot = quat_to_rotmat(s.quats.detach()[rep])
    means = (rot @ samples.unsqueeze(-1)).squeeze(-1) + s.means.detach()[rep]
    return rep, {"means": means, "log_scales": torch.log(std / SPLIT_SCALE_DIVISOR)}


def split(opt: SceneOptimizer, mask: torch.Tensor, state: Optional[dict[str, torch.Tensor]] = None,
          generator: Optional[torch.Generator] = None) -> int:
    """Replace each Gaussian in ``mask`` by two children sampled from it (positions drawn from
    the parent's Gaussian, scales divided by 1.6, INRIA's split); the children go to the end.
    Returns the number of Gaussians split."""
    idx = torch.nonzero(_mask(opt, mask, "split")).reshape(-1)
    if idx.numel() == 0:
        return 0
    rep, overrides = _split_children(opt, idx, generator)
    opt.edit_rows(keep=~mask.to(opt.scene.device), parents=rep, state=state, overrides=overrides)
    return int(idx.numel())


def clone_and_split(opt: SceneOptimizer, clone: torch.Tensor, split_mask: torch.Tensor,
                    state: Optional[dict[str, torch.Tensor]] = None,
                    generator: Optional[torch.Generator] = None) -> tuple[int, int]:
    """:func:`duplicate` the rows of ``clone`` and then :func:`split` those of ``split_mask``
    (both [N] bool; a row in both is cloned, then split, as by the two calls), in one row surgery:
    the same rows, moments and random draws as the two calls (kept rows, then the clones, then
    the split children), but every parameter,
    Adam moment and extra is gathered and concatenated once instead of twice (a densification's
    host work and launches, halved). Returns (cloned, split) counts."""
    parents = torch.nonzero(_mask(opt, clone, "clone")).reshape(-1)
    split_mask = _mask(opt, split_mask, "split")
    idx = torch.nonzero(split_mask).reshape(-1)
    if idx.numel() == 0:
        if parents.numel():
            opt.edit_rows(parents=parents, state=state)
        return int(parents.numel()), 0
    rep, children = _split_children(opt, idx, generator)
    s = opt.scene
    overrides = {name: torch.cat([getattr(s, name).detach()[parents], v]) for name, v in children.items()}
    opt.edit_rows(keep=~split_mask, parents=torch.cat([parents, rep]), state=state, overrides=overrides)
    return int(parents.numel()), int(idx.numel())


def remove(opt: SceneOptimizer, mask: torch.Tensor, state: Optional[dict[str, torch.Tensor]] = None) -> int:
    """Delete the Gaussians in ``mask`` (parameters, Adam rows, extras, ``state`` rows)."""
    mask = _mask(opt, mask, "remove")
    n = int(mask.sum())
    if n:  # none: no row surgery (an edit's densification seldom prunes)
        opt.edit_rows(keep=~mask, state=state)
    return n


def reset_opacity(opt: SceneOptimizer, max_opacity: float = 0.01, mask: Optional[torch.Tensor] = None) -> None:
    """Clamp the opacity of the Gaussians in ``mask`` (default all) to at most ``max_opacity``
    and zero their opacity moments (INRIA's reset)."""
    s = opt.scene
    rows = torch.ones(len(s), dtype=torch.bool, device=s.device) if mask is None else _mask(opt, mask, "reset_opacity")
    with torch.no_grad():
        op = torch.minimum(s.opacities.detach(), torch.full_like(s.opacity_logits, max_opacity))
        opt.set_rows("opacity_logits", rows, inverse_sigmoid(op))


__all__ = ["clone_and_split", "duplicate", "split", "remove", "reset_opacity", "SPLIT_CHILDREN", "SPLIT_SCALE_DIVISOR"]
