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

The attachment rule bounds all three, so that a rule adds only what is joined to the object and
takes nothing from another object. Without it the box rules, made for an object standing on a
support, grow the deletion of the support (a table, whose box holds everything on it) into all
that stands on it: the mug's hidden bottom (unseen), its base blended into the table's language
(floaters), the table-brown cardboard box (appearance). Each rule asks the ``attach_k`` nearest
Gaussians:
  * floater: at least half of its neighbours that have language evidence (or are removed) are
    removed; grown from the retrieved object outward;
  * unseen: at least half of its ``attach_k`` nearest Gaussians *with* language evidence are
    removed; decided at once, not grown through the unseen ones (a patch no view saw where two
    objects meet would be flooded from any one contact);
  * appearance: its removed neighbours outnumber its kept neighbours that show the candidate's
    colour to be a thing of its own (colour closer to the candidate's than ``appearance_margin``
    times its distance to the retrieved object's colours: the box's cardboard beside the table);
    kept neighbours of the object's own colour abstain (the rest of a band of the object that the
    language field missed).
``attach_k = 0`` turns it off.
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
                 sizes: Optional[torch.Tensor] = None, attach_k: int = 8) -> Removal:
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
        attach_k: neighbours of the attachment rule (0: off).
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
    if attach_k < 0:
        raise ValueError(f"tiger.delete.removal_mask: attach_k must be >= 0, got {attach_k}")
    unseen = torch.zeros_like(retrieved)
    evidence = torch.ones_like(retrieved)  # language evidence: unknown without lang_norms
    if lang_norms is not None:
        if lang_norms.shape != (n,):
            raise ValueError(f"tiger.delete.removal_mask: lang_norms must be [N={n}], got {list(lang_norms.shape)}")
        norms = lang_norms.detach().to(means.device, torch.float64)
        evidence = norms > unseen_norm * float(norms[retrieved].median())
        unseen = inside & ~evidence & ~retrieved
    # a featureless Gaussian's score (0) says nothing: it is never a floater, only unseen
    floaters = inside & evidence & (s > float(floater_tau)) & ~retrieved
    if attach_k > 0:  # the attachment rule (module docstring)
        floaters = _grow_attached(m, retrieved & inside, floaters, inside, evidence, attach_k)
        unseen = _vote_unseen(m, (retrieved & inside) | floaters, unseen, inside & evidence, attach_k)
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
                              None if sizes is None else float(sizes.detach().to(m.device)[gone].float().median()),
                              attach_k=attach_k, core=retrieved & inside)
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


def _neighbours(p: torch.Tensor, rows: torch.Tensor, k: int, chunk: int = 1024) -> torch.Tensor:
    """[R, k'] indices into ``p`` [P, 3] of the ``k' = min(k, P - 1)`` nearest other points of
    each ``p[rows]`` (chunked: no R x P matrix)."""
    k = min(int(k), p.shape[0] - 1)
    out = []
    for s in range(0, rows.numel(), chunk):
        r = rows[s:s + chunk]
        d = torch.cdist(p[r], p, compute_mode=_EXACT)
        d[torch.arange(r.numel(), device=d.device), r] = float("inf")  # the point itself
        out.append(d.topk(k, dim=1, largest=False).indices)
    return torch.cat(out) if out else torch.zeros(0, max(k, 0), dtype=torch.long, device=p.device)


def _attached(gone: torch.Tensor, voters: torch.Tensor, nbr: torch.Tensor) -> torch.Tensor:
    """[R] bool: at least half of the voting neighbours of each row removed (``nbr`` [R, k]
    indices into ``gone`` and ``voters``, [P] bool; a removed Gaussian always votes)."""
    votes = (gone | voters)[nbr].sum(dim=1)
    return (votes > 0) & (2 * gone[nbr].sum(dim=1) >= votes)


def _grow_attached(means: torch.Tensor, removed: torch.Tensor, candidates: torch.Tensor,
                   region: torch.Tensor, evidence: torch.Tensor, k: int) -> torch.Tensor:
    """[N] bool: the ``candidates`` (within ``region``, both [N] bool) that join ``removed`` [N]
    bool by the attachment rule (module docstring): repeatedly add each candidate at least half of
    whose ``k`` nearest Gaussians of the region that vote (removed, or with language
    ``evidence`` [N] bool) are removed, until none joins."""
    idx = torch.nonzero(region).reshape(-1)
    gone = removed[idx].clone()
    cand = candidates[idx] & ~gone
    added = torch.zeros_like(removed)
    if idx.numel() < 2 or not bool(cand.any()):
        return added
    rows = torch.nonzero(cand).reshape(-1)
    nbr = _neighbours(means[idx].float(), rows, k)
    voters = evidence[idx]
    waiting = torch.ones(rows.numel(), dtype=torch.bool, device=rows.device)
    while True:
        new = waiting & _attached(gone, voters, nbr)
        if not bool(new.any()):
            break
        gone[rows[new]] = True
        waiting &= ~new
    added[idx] = gone & ~removed[idx]
    return added


def _vote_unseen(means: torch.Tensor, removed: torch.Tensor, unseen: torch.Tensor, voters: torch.Tensor,
                 k: int, chunk: int = 1024) -> torch.Tensor:
    """[N] bool: the ``unseen`` Gaussians (no language evidence) that at least half of their ``k``
    nearest ``voters`` (with evidence, [N] bool) vote away: those ``removed`` [N] bool. Decided
    at once, not grown: an unseen patch where the object meets another (the mug's bottom on the
    table) goes to whichever the seen Gaussians around each of its Gaussians are."""
    out = torch.zeros_like(unseen)
    rows, refs = torch.nonzero(unseen).reshape(-1), torch.nonzero(voters).reshape(-1)
    if rows.numel() == 0 or refs.numel() == 0:
        return out
    kk = min(int(k), refs.numel())
    pr = means[refs].float()
    gone = removed[refs]
    for s in range(0, rows.numel(), chunk):
        r = rows[s:s + chunk]
        nb = torch.cdist(means[r].float(), pr, compute_mode=_EXACT).topk(kk, dim=1, largest=False).indices
        out[r] = 2 * gone[nb].sum(dim=1) >= kk
    return out


def _appearance(means: torch.Tensor, colors: torch.Tensor, inside: torch.Tensor, shell: torch.Tensor,
                allowed: torch.Tensor, removed: torch.Tensor, margin: float, iters: int,
                radius: Optional[float], size: Optional[float] = None, k: int = 8,
                max_refs: int = 4096, attach_k: int = 8, core: Optional[torch.Tensor] = None) -> torch.Tensor:
    """The appearance rule (module docstring) on means [N,3] and colours [N,3]: candidates in
    ``allowed``, surroundings' colours from the kept ones in ``shell`` (both [N] bool within
    ``inside``), bounded by the attachment rule over ``attach_k`` neighbours (0: off; voters: the
    removed, and the kept ones of the candidate's colour rather than the colours of ``core`` [N]
    bool, the retrieved object; default: ``removed``); memory
    O(N), no N x N matrices (scenes of millions of Gaussians have boxes of tens of thousands)."""
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
    # the attachment rule's neighbours, for every Gaussian the rule could ever add
    open_rows = torch.nonzero(~gone & allowed_i).reshape(-1)
    slot = torch.full((p.shape[0],), -1, dtype=torch.long, device=p.device)
    slot[open_rows] = torch.arange(open_rows.numel(), device=p.device)
    nbr = _neighbours(p, open_rows, attach_k) if attach_k > 0 else None
    # the object's own colours for the attachment votes: the retrieved ones, not what the rules
    # added (a rule's mistake must not make the next one look right)
    core_c = _subsample(c[core[idx]] if core is not None and bool(core[idx].any()) else c[gone], max_refs,
                        torch.Generator().manual_seed(2))
    for _ in range(max(int(iters), 0)):
        cand = ~gone & (dist <= radius) & allowed_i
        if not bool(cand.any()) or int(ref_kept.sum()) == 0:
            break
        # the nearest eighth of the object's colours and the nearest quarter of the surroundings',
        # on random subsets of at most ``max_refs`` each (the fractions are what matter)
        obj_c, ref_c = _subsample(c[gone], max_refs, gen), _subsample(c[ref_kept], max_refs, gen)
        cand_rows = torch.nonzero(cand).reshape(-1)
        to_obj = _mean_nearest(c[cand], obj_c, min(max(k, obj_c.shape[0] // 8), obj_c.shape[0]))
        to_rest = _mean_nearest(c[cand], ref_c, min(max(k, ref_c.shape[0] // 4), ref_c.shape[0]))
        ok = to_obj < margin * to_rest
        if nbr is not None and bool(ok.any()):
            # attachment: the removed neighbours vote for, and a kept neighbour votes against when
            # it shows the candidate's colour to be a thing of its own (its colour much closer to
            # the candidate's than to the object's); the others, the object's colour, abstain
            nb = nbr[slot[cand_rows]]
            kept_nb = torch.unique(nb[~gone[nb]])
            to_obj_nb = torch.full((p.shape[0],), float("inf"), dtype=p.dtype, device=p.device)
            to_obj_nb[kept_nb] = _mean_nearest(c[kept_nb], core_c, min(max(k, core_c.shape[0] // 8), core_c.shape[0]))
            own = (c[nb] - c[cand_rows][:, None]).norm(dim=-1) < margin * to_obj_nb[nb]
            against = (~gone[nb] & own).sum(dim=1)
            ok &= gone[nb].sum(dim=1) > against
        new = torch.zeros_like(gone)
        new[cand_rows] = ok
        if not bool(new.any()):
            break
        gone |= new
        ref_kept &= ~new
        rest = ~gone
        dist[rest] = torch.minimum(dist[rest], _min_dist(p[rest], p[new]))
    added[idx] = gone & ~removed[idx]
    return added
