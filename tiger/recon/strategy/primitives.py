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


def _grow(opt: SceneOptimizer, parents: torch.Tensor, split_rows: torch.Tensor, split_mask: Optional[torch.Tensor],
          state: Optional[dict[str, torch.Tensor]], generator: Optional[torch.Generator]) -> None:
    """The one row surgery of the growing primitives: a copy of each row of ``parents`` [P], then
    rows ``split_rows`` [K] (``split_mask`` [N] bool) replaced by two children each, sampled from
    the parent (positions drawn from its Gaussian, scales divided by 1.6, INRIA's split). New
    order: kept rows, the copies, the split children. Nothing to do: no surgery (it would copy
    every tensor and Adam row unchanged)."""
    if parents.numel() == 0 and split_rows.numel() == 0:
        return
    if split_rows.numel() == 0:
        opt.edit_rows(parents=parents, state=state)
        return
    s = opt.scene
    rep = split_rows.repeat(SPLIT_CHILDREN)
    std = s.scales.detach()[rep]
    samples = torch.randn(std.shape, generator=generator, dtype=std.dtype).to(std.device) * std
    rot = quat_to_rotmat(s.quats.detach()[rep])
    children = {"means": (rot @ samples.unsqueeze(-1)).squeeze(-1) + s.means.detach()[rep],
                "log_scales": torch.log(std / SPLIT_SCALE_DIVISOR)}
    overrides = {name: torch.cat([getattr(s, name).detach()[parents], v]) for name, v in children.items()}
    opt.edit_rows(keep=~split_mask, parents=torch.cat([parents, rep]), state=state, overrides=overrides)


def _rows(mask: torch.Tensor) -> torch.Tensor:
    return torch.nonzero(mask).reshape(-1)


def duplicate(opt: SceneOptimizer, mask: torch.Tensor, state: Optional[dict[str, torch.Tensor]] = None) -> int:
    """Append an identical copy of each Gaussian in ``mask`` (INRIA's clone); returns the count."""
    parents = _rows(_mask(opt, mask, "duplicate"))
    _grow(opt, parents, parents[:0], None, state, None)
    return int(parents.numel())


def split(opt: SceneOptimizer, mask: torch.Tensor, state: Optional[dict[str, torch.Tensor]] = None,
          generator: Optional[torch.Generator] = None) -> int:
    """Replace each Gaussian in ``mask`` by two children sampled from it (positions drawn from
    the parent's Gaussian, scales divided by 1.6, INRIA's split); the children go to the end.
    Returns the number of Gaussians split."""
    mask = _mask(opt, mask, "split")
    idx = _rows(mask)
    _grow(opt, idx[:0], idx, mask, state, generator)
    return int(idx.numel())


def clone_and_split(opt: SceneOptimizer, clone: torch.Tensor, split_mask: torch.Tensor,
                    state: Optional[dict[str, torch.Tensor]] = None,
                    generator: Optional[torch.Generator] = None) -> tuple[int, int]:
    """:func:`duplicate` the rows of ``clone`` and then :func:`split` those of ``split_mask``
    (both [N] bool; a row in both is cloned, then split, as by the two calls), in one row surgery:
    the same rows, moments and random draws as the two calls (kept rows, then the clones, then
    the split children), but every parameter, Adam moment and extra is gathered and concatenated
    once instead of twice (a densification's host work and launches, halved). Returns (cloned,
    split) counts."""
    parents = _rows(_mask(opt, clone, "clone"))
    split_mask = _mask(opt, split_mask, "split")
    idx = _rows(split_mask)
    _grow(opt, parents, idx, split_mask, state, generator)
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
