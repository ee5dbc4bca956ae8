"""Which Gaussians a deletion removes: the retrieved object plus the floaters that belong to it.

Retrieval (``s > tau``) finds the object's body, but an object's reconstruction also leaves
semi-transparent floaters and border Gaussians whose language embedding is a blend of the object
and its surroundings: their relevance sits between the background's and ``tau``. Left in the
scene they show up as ghosts after the deletion (GaussianEditor's users report exactly that).

The floater rule: a Gaussian is also removed when
  1. its centre lies inside the object's robust box (per-axis quantiles ``box_quantiles`` of the
     retrieved centres), grown on every side by ``box_margin`` times the box's largest side, and
  2. its score is above the lower threshold
     ``floater_tau = median(scores) + floater_fraction * (tau - median(scores))``
     (half-way between a typical Gaussian and the retrieval threshold by default).
Gaussians of the surroundings inside the box (the table under a mug) score near the median and
stay; stray Gaussians outside the grown box stay whatever their score, retrieved ones included
(a few Gaussians of the neighbouring objects lean toward the text; deleting the ball must not
take them). ``floater_fraction = 1`` turns the rule off.

The unseen rule: a Gaussian inside the same box whose language feature is (nearly) zero, with a
norm below ``unseen_norm`` times the median norm of the retrieved ones, is removed too. Language
training leaves a Gaussian's feature at zero when no training view sees it: inside the box these
are the parts the object hid from every view (a mug's inner wall and bottom). Their relevance
says nothing; left in place they would surface once the object is gone.

The appearance rule (when ``colors`` are given): where the language field blurs the object into
its support (a mug's bottom band, a ball's underside trained toward "table"), a kept Gaussian
inside the robust box grown by ``appearance_reach`` margins that touches the removed ones (within
``radius``; default 3x the median nearest-neighbour spacing of the removed Gaussians, or twice
their median size (``sizes``, the largest axis) when larger: such surfels overlap) is removed
when its colour is much closer to the object's colours than to the surroundings': mean colour
distance to its nearest eighth of the object's colours < ``appearance_margin`` x the mean
distance to its nearest quarter of the surrounding colours (fractions, not single neighbours, so
that a few misretrieved Gaussians in the object or a few object-coloured ones around do not
decide). The surroundings are the kept Gaussians in the next margin *outside* that region (the
table around a ball), never the candidates themselves: an unretrieved part of the object (the
ball's underside) cannot vote for itself. Repeated up to ``appearance_iters`` times, so it grows
along the object inside the region only. ``appearance_margin = None`` turns it off.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import torch

from tiger.retrieval import robust_bounds


@dataclass
class Removal:
    """The Gaussians a deletion removes (all masks [N] bool over the scene before deletion).

    Attributes:
        mask: everything removed: the retrieved Gaussians inside the grown box, the floaters,
            the unseen and the similar ones.
        retrieved: the retrieval's selection (``scores > tau``).
        floaters: added by the floater rule (not retrieved).
        unseen: added by the unseen rule (neither retrieved nor floaters).
        similar: added by the appearance rule (none of the above).
        stray: retrieved but outside the grown box, so kept: a few Gaussians of other objects
            whose language leans toward the text (far from the object, they are not part of it).
        tau, floater_tau: the two thresholds on the scores.
        box_min, box_max: [3] the grown robust box of the retrieved centres (world units).
    """

    mask: torch.Tensor
    retrieved: torch.Tensor
    floaters: torch.Tensor
    unseen: torch.Tensor
    similar: torch.Tensor
    stray: torch.Tensor
    tau: float
    floater_tau: float
    box_min: torch.Tensor
    box_max: torch.Tensor

    def counts(self) -> dict[str, int]:
        return {"retrieved": int(self.retrieved.sum()), "floaters": int(self.floaters.sum()),
                "unseen": int(self.unseen.sum()), "similar": int(self.similar.sum()),
                "stray_kept": int(self.stray.sum()), "removed": int(self.mask.sum()), "total": int(self.mask.numel()),
                "kept": int((~self.mask).sum())}


def removal_mask(scores: torch.Tensor, retrieved: torch.Tensor, means: torch.Tensor, tau: float, *,
                 floater_fraction: float = 0.5, box_margin: float = 0.1,
                 box_quantiles: tuple[float, float] = (0.02, 0.98),
                 floater_tau: Optional[float] = None, lang_norms: Optional[torch.Tensor] = None,
                 unseen_norm: float = 0.1, colors: Optional[torch.Tensor] = None,
                 appearance_margin: Optional[float] = 0.5, appearance_iters: int = 50,
                 appearance_reach: float = 2.0, radius: Optional[float] = None,
                 sizes: Optional[torch.Tensor] = None) -> Removal:
    """Apply the floater rule (module docstring) around a retrieval.

    Args:
        scores: [N] the retrieval's per-Gaussian scores (cosine or relevancy).
        retrieved: [N] bool, the retrieval's selection.
        means: [N, 3] Gaussian centres.
        tau: the retrieval threshold (``retrieved == scores > tau`` for a text retrieval).
        floater_fraction: where the lower threshold sits between the median score (0) and tau (1).
        box_margin: growth of the robust box on each side, as a fraction of its largest side.
        box_quantiles: per-axis quantiles of the retrieved centres spanning the box.
        floater_tau: an explicit lower threshold (overrides ``floater_fraction``).
        lang_norms: [N] norms of the language features, for the unseen rule (None: rule off).
        unseen_norm: the unseen rule's relative norm threshold.
        colors: [N, 3] Gaussian colours for the appearance rule (None: rule off).
        appearance_margin, appearance_iters, appearance_reach, radius: the appearance rule's
            parameters (``appearance_reach``: how many box margins its candidates may lie outside
            the robust box); ``sizes`` [N]: each Gaussian's largest axis (world units), for the
            default radius.
    Returns:
        a :class:`Removal`.
    """
    n = means.shape[0] if means.dim() == 2 else -1
    if means.dim() != 2 or means.shape[1] != 3:
        raise ValueError(f"tiger.delete.removal_mask: means must be [N, 3], got {list(means.shape)}")
    if scores.shape != (n,) or retrieved.shape != (n,) or retrieved.dtype != torch.bool:
        raise ValueError(f"tiger.delete.removal_mask: scores and retrieved must be [N={n}] (float, bool), "
                         f"got {list(scores.shape)} {scores.dtype} and {list(retrieved.shape)} {retrieved.dtype}")
    if not 0.0 <= floater_fraction <= 1.0 or box_margin < 0:
        raise ValueError(f"tiger.delete.removal_mask: need 0 <= floater_fraction <= 1 and box_margin >= 0, "
                         f"got {floater_fraction} and {box_margin}")
    retrieved = retrieved.to(means.device)
    if not bool(retrieved.any()):
        raise ValueError("tiger.delete.removal_mask: the retrieval selected no Gaussian: nothing to delete")
    s = scores.detach().to(means.device, torch.float64)
    _, lo, hi = robust_bounds(means.detach()[retrieved], box_quantiles)
    tight_lo, tight_hi = lo.clone(), hi.clone()
    grow = box_margin * float((hi - lo).max())
    lo, hi = lo - grow, hi + grow
    m = means.detach().to(torch.float64)
    inside = ((m >= lo.to(m.device)) & (m <= hi.to(m.device))).all(dim=1)
    if floater_tau is None:
        med = float(s.median())
        floater_tau = med + floater_fraction * (float(tau) - med)
    floaters = inside & (s > float(floater_tau)) & ~retrieved
    unseen = torch.zeros_like(retrieved)
    if lang_norms is not None:
        if lang_norms.shape != (n,):
            raise ValueError(f"tiger.delete.removal_mask: lang_norms must be [N={n}], got {list(lang_norms.shape)}")
        norms = lang_norms.detach().to(means.device, torch.float64)
        unseen = inside & (norms <= unseen_norm * float(norms[retrieved].median())) & ~retrieved & ~floaters
    similar = torch.zeros_like(retrieved)
    if colors is not None and appearance_margin is not None:
        if colors.shape != (n, 3):
            raise ValueError(f"tiger.delete.removal_mask: colors must be [N={n}, 3], got {list(colors.shape)}")
        def in_box(k: float) -> torch.Tensor:  # the robust box grown by k margins
            lo_k, hi_k = (tight_lo - k * grow).to(m.device), (tight_hi + k * grow).to(m.device)
            return ((m >= lo_k) & (m <= hi_k)).all(dim=1)

        near = in_box(appearance_reach)
        ring = in_box(appearance_reach + 1) & ~near
        gone = retrieved | floaters | unseen
        if not bool((ring & ~gone).any()):  # nothing around the box: the margin inside it
            ring = inside & ~in_box(0)
        similar = _appearance(m, colors.detach().to(means.device, torch.float64), near | ring, ring, near,
                              gone, appearance_margin, appearance_iters, radius,
                              None if sizes is None else float(sizes.detach().to(m.device)[gone].float().median()))
    stray = retrieved & ~inside
    return Removal(mask=(retrieved & inside) | floaters | unseen | similar, retrieved=retrieved, floaters=floaters,
                   unseen=unseen, similar=similar, stray=stray, tau=float(tau),
                   floater_tau=float(floater_tau), box_min=lo.float(), box_max=hi.float())


_EXACT = "donot_use_mm_for_euclid_dist"  # the matmul form is off by ~1e-4 for identical points


def _min_dist(a: torch.Tensor, b: torch.Tensor, chunk: int = 2048) -> torch.Tensor:
    """[A] distance from each row of ``a`` to its nearest row of ``b`` (chunked: no A x B matrix)."""
    if b.shape[0] == 0:
        return torch.full((a.shape[0],), float("inf"), dtype=a.dtype, device=a.device)
    return torch.cat([torch.cdist(a[s:s + chunk], b, compute_mode=_EXACT).min(1).values for s in range(0, a.shape[0], chunk)]) \
        if a.shape[0] else a.new_zeros(0)


def _mean_nearest(a: torch.Tensor, b: torch.Tensor, k: int, chunk: int = 1024) -> torch.Tensor:
    """[A] mean distance from each row of ``a`` to its ``k`` nearest rows of ``b`` (chunked)."""
    return torch.cat([torch.cdist(a[s:s + chunk], b, compute_mode=_EXACT).topk(k, dim=1, largest=False).values.mean(1)
                      for s in range(0, a.shape[0], chunk)]) if a.shape[0] else a.new_zeros(0)


def _subsample(x: torch.Tensor, n: int, gen: torch.Generator) -> torch.Tensor:
    """At most ``n`` random rows of ``x``."""
    if x.shape[0] <= n:
        return x
    return x[torch.randperm(x.shape[0], generator=gen)[:n].to(x.device)]


def _appearance(means: torch.Tensor, colors: torch.Tensor, inside: torch.Tensor, shell: torch.Tensor,
                allowed: torch.Tensor, removed: torch.Tensor, margin: float, iters: int,
                radius: Optional[float], size: Optional[float] = None, k: int = 8,
                max_refs: int = 4096) -> torch.Tensor:
    """The appearance rule (module docstring) on means [N,3] and colours [N,3]: candidates in
    ``allowed``, surroundings' colours from the kept ones in ``shell`` (both [N] bool within
    ``inside``); memory O(N), no N x N matrices (scenes of millions of Gaussians have boxes of
    tens of thousands)."""
    idx = torch.nonzero(inside).reshape(-1)
    allowed_i = allowed[idx]
    added = torch.zeros_like(removed)
    gone = removed[idx].clone()
    if idx.numel() < 2 or int(gone.sum()) < 2 or bool(gone.all()):
        return added
    p, c = means[idx].float(), colors[idx].float()
    ref_kept = shell[idx] & ~gone  # the surroundings: kept, in the margin around the object's box
    if int(ref_kept.sum()) == 0:
        return added
    if radius is None:
        obj = p[gone]
        pick = torch.randperm(obj.shape[0], generator=torch.Generator().manual_seed(0))[:4096].to(obj.device)
        d = torch.cdist(obj[pick], obj, compute_mode=_EXACT)
        d[torch.arange(pick.numel(), device=d.device), pick] = float("inf")  # the point itself
        radius = max(3.0 * float(d.min(1).values.median()), 2.0 * (size or 0.0))  # overlapping surfels touch
    # distance of each kept box Gaussian to the removed ones (only kept ones can be candidates)
    dist = torch.full((p.shape[0],), float("inf"), dtype=p.dtype, device=p.device)
    dist[~gone] = _min_dist(p[~gone], p[gone])
    gen = torch.Generator().manual_seed(1)
    for _ in range(max(int(iters), 0)):
        cand = ~gone & (dist <= radius) & allowed_i
        if not bool(cand.any()) or int(ref_kept.sum()) == 0:
            break
        # the nearest eighth of the object's colours and the nearest quarter of the surroundings',
        # on random subsets of at most ``max_refs`` each (the fractions are what matter)
        obj_c, ref_c = _subsample(c[gone], max_refs, gen), _subsample(c[ref_kept], max_refs, gen)
        to_obj = _mean_nearest(c[cand], obj_c, min(max(k, obj_c.shape[0] // 8), obj_c.shape[0]))
        to_rest = _mean_nearest(c[cand], ref_c, min(max(k, ref_c.shape[0] // 4), ref_c.shape[0]))
        new = torch.zeros_like(gone)
        new[torch.nonzero(cand).reshape(-1)] = to_obj < margin * to_rest
        if not bool(new.any()):
            break
        gone |= new
        ref_kept &= ~new
        rest = ~gone
        dist[rest] = torch.minimum(dist[rest], _min_dist(p[rest], p[new]))
    added[idx] = gone & ~removed[idx]
    return added
