"""A sanity check of a selection before it is edited or deleted: one object, not the scene.

A wrong threshold does not fail loudly: it selects the table with the mug, or every object on it,
and an edit or a deletion then changes all of that. Two signs give such a selection away:

* **share**: it holds more than ``max_share`` of the scene's Gaussians (an object rarely does;
  the largest surface of a scene may, and then the check says so and the caller may go on);
* **compactness**: its Gaussians fall into several separate groups in space. Groups are the
  connected parts of the selection when Gaussians closer than ``link`` times the scene's size
  (the diagonal of its 2 %-98 % box) are joined (single linkage on a voxel grid of that cell
  size, so the cost is linear in the selection). A group counts when it holds at least
  ``min_group`` of the selection (a few stray Gaussians are not a second object).

``tiger query`` prints the problem as a warning; ``tiger edit`` and ``tiger delete`` refuse such
a selection unless ``--force`` is given.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import torch

#: A selection holding more than this share of the scene's Gaussians is suspect.
MAX_SHARE = 0.5
#: Gaussians closer than this fraction of the scene's diagonal belong to one group.
LINK = 0.05
#: A group counts when it holds at least this share of the selection.
MIN_GROUP = 0.1

_OFFSETS = [(dx, dy, dz) for dx in (-1, 0, 1) for dy in (-1, 0, 1) for dz in (-1, 0, 1)
            if (dx, dy, dz) != (0, 0, 0)]


@dataclass
class SelectionCheck:
    """What :func:`check_selection` found.

    Attributes:
        selected, total: Gaussians selected and in the scene.
        share: ``selected / total``.
        groups: sizes of the selection's separate groups holding at least ``min_group`` of it,
            largest first.
        problem: one line naming what is wrong, or None when the selection looks like one object.
    """

    selected: int
    total: int
    share: float
    groups: list[int]
    problem: Optional[str]

    @property
    def ok(self) -> bool:
        return self.problem is None


def connected_groups(points: torch.Tensor, radius: float) -> torch.Tensor:
    """[K] int64 group index of each of ``points`` [K, 3]: the connected parts when points in the
    same or neighbouring cells of a ``radius`` voxel grid are joined (every pair closer than
    ``radius`` is joined; pairs up to ``2 sqrt(3) radius`` may be). Indices are 0..G-1."""
    if points.dim() != 2 or points.shape[1] != 3:
        raise ValueError(f"tiger.retrieval: points must be [K, 3], got {list(points.shape)}")
    if points.shape[0] == 0:
        return torch.zeros(0, dtype=torch.int64, device=points.device)
    if not radius > 0:
        raise ValueError(f"tiger.retrieval: radius must be > 0, got {radius}")
    cells = torch.floor(points.detach().to(torch.float64) / radius).to(torch.int64)
    cells = cells - cells.min(dim=0).values + 1  # one empty cell of padding on each side
    size = cells.max(dim=0).values + 2
    sy, sz = int(size[1]), int(size[2])
    keys = (cells[:, 0] * sy + cells[:, 1]) * sz + cells[:, 2]
    uniq, inverse = torch.unique(keys, return_inverse=True)  # sorted
    label = torch.arange(uniq.numel(), device=points.device)
    neighbours = []
    for dx, dy, dz in _OFFSETS:
        nk = uniq + (dx * sy + dy) * sz + dz
        pos = torch.searchsorted(uniq, nk).clamp_max(uniq.numel() - 1)
        hit = uniq[pos] == nk
        neighbours.append((torch.nonzero(hit).reshape(-1), pos[hit]))
    while True:  # propagate the smallest label through the cell graph, with pointer jumping
        new = label.clone()
        for a, b in neighbours:
            new.scatter_reduce_(0, a, label[b], reduce="amin")
        new = new[new]
        if torch.equal(new, label):
            break
        label = new
    _, group = torch.unique(label, return_inverse=True)
    return group[inverse]


def check_selection(means: torch.Tensor, mask: torch.Tensor, *, max_share: float = MAX_SHARE,
                    link: float = LINK, min_group: float = MIN_GROUP) -> SelectionCheck:
    """Check that ``mask`` [N] bool over a scene's Gaussians with centres ``means`` [N, 3] looks like
    one object (module docstring). An empty selection is reported as a problem too."""
    n = means.shape[0]
    if mask.shape != (n,) or mask.dtype != torch.bool:
        raise ValueError(f"tiger.retrieval: mask must be [N={n}] bool, got {list(mask.shape)} {mask.dtype}")
    k = int(mask.sum())
    share = k / max(n, 1)
    if k == 0:
        return SelectionCheck(0, n, 0.0, [], "it selects no Gaussian")
    if share > max_share:
        return SelectionCheck(k, n, share, [k], f"it selects {share:.0%} of the scene's Gaussians "
                              f"({k} of {n}): more than one object")
    m = means.detach().to(torch.float64)
    lo = torch.quantile(m, 0.02, dim=0) if n <= 1 << 24 else m.min(dim=0).values
    hi = torch.quantile(m, 0.98, dim=0) if n <= 1 << 24 else m.max(dim=0).values
    diagonal = float((hi - lo).norm())
    groups: list[int] = [k]
    if diagonal > 0 and k > 1:
        sizes = torch.bincount(connected_groups(m[mask.to(m.device)], link * diagonal))
        groups = sorted((int(v) for v in sizes if int(v) >= min_group * k), reverse=True)
    if len(groups) > 1:
        return SelectionCheck(k, n, share, groups, f"its {k} Gaussians fall into {len(groups)} separate "
                              f"groups ({', '.join(map(str, groups))} Gaussians): not one compact object")
    return SelectionCheck(k, n, share, groups, None)


__all__ = ["LINK", "MAX_SHARE", "MIN_GROUP", "SelectionCheck", "check_selection", "connected_groups"]
