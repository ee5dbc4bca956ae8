"""3D retrieval: per-Gaussian relevance to a text query, selection ``s > tau``, object bounds."""
from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import NamedTuple, Optional, Sequence, Union

import torch

from tiger.scene import GaussianScene

from .relevance import DEFAULT_TEMPERATURE, relevancy
from .text import CANONICAL_NEGATIVES, PCASource, Query, TextEncoder, embed_negatives, embed_queries

log = logging.getLogger(__name__)

Tau = Union[None, str, float]


class _Histogram(NamedTuple):
    hist: Optional[torch.Tensor]  # [bins] counts; None when fewer than two distinct values
    centres: Optional[torch.Tensor]  # [bins] bin centres
    lo: float
    hi: float
    width: float


def _histogram(scores: torch.Tensor, bins: int) -> _Histogram:
    """The finite ``scores`` (any shape) in ``bins`` equal float64 bins over [min, max]."""
    s = scores.detach().reshape(-1).to(torch.float64)
    s = s[torch.isfinite(s)]
    if s.numel() == 0:
        raise ValueError("tiger.retrieval: no finite scores to threshold")
    lo, hi = float(s.min()), float(s.max())
    if not hi > lo:
        return _Histogram(None, None, lo, hi, 0.0)
    width = (hi - lo) / bins
    centres = lo + (torch.arange(bins, dtype=torch.float64, device=s.device) + 0.5) * width
    return _Histogram(torch.histc(s, bins=bins, min=lo, max=hi), centres, lo, hi, width)


def otsu_threshold(scores: torch.Tensor, bins: int = 512) -> float:
    """Otsu's threshold of ``scores`` [K]: the cut maximising the between-class variance.

    The scores are histogrammed into ``bins`` equal bins over [min, max]; the returned value is the
    upper edge of the last bin of the lower class, so ``scores > tau`` is the upper class. With
    fewer than two distinct values there is nothing to separate and the maximum is returned
    (``scores > tau`` then selects nothing).
    """
    h = _histogram(scores, bins)
    if h.hist is None:
        return h.hi
    hist, centres, lo, width = h.hist, h.centres, h.lo, h.width
    w0 = torch.cumsum(hist, 0)
    m0 = torch.cumsum(hist * centres, 0)
    total, total_m = w0[-1], m0[-1]
    w1 = total - w0
    valid = (w0 > 0) & (w1 > 0)
    mu0 = m0 / w0.clamp_min(1)
    mu1 = (total_m - m0) / w1.clamp_min(1)
    between = torch.where(valid, w0 * w1 * (mu0 - mu1) ** 2, torch.full_like(w0, -1.0))
    k = int(torch.argmax(between))
    return lo + (k + 1) * width


def min_error_threshold(scores: torch.Tensor, bins: int = 512) -> float:
    """Kittler-Illingworth minimum-error threshold of ``scores`` [K].

    Fits the histogram (``bins`` equal bins over [min, max]) with two normal classes, each with its
    own weight and variance, and returns the cut minimising the classification-error criterion
    ``J = P0 ln s0^2 + P1 ln s1^2 - 2 (P0 ln P0 + P1 ln P1)``. Unlike Otsu's threshold it does not
    drift into the large class when the object is a small fraction of the scene (the usual case in
    retrieval: 1 % object -> Otsu cuts inside the background). Variances are floored at the bin
    quantisation (width^2 / 12). Fewer than two distinct values: the maximum is returned.
    """
    h = _histogram(scores, bins)
    if h.hist is None:
        return h.hi
    hist, c, lo, width = h.hist, h.centres, h.lo, h.width
    w0, m0, q0 = hist.cumsum(0), (hist * c).cumsum(0), (hist * c * c).cumsum(0)
    total = w0[-1]
    w1, m1, q1 = total - w0, m0[-1] - m0, q0[-1] - q0
    valid = (w0 > 0) & (w1 > 0)
    mu0, mu1 = m0 / w0.clamp_min(1), m1 / w1.clamp_min(1)
    floor = width * width / 12
    v0 = (q0 / w0.clamp_min(1) - mu0 * mu0).clamp_min(floor)
    v1 = (q1 / w1.clamp_min(1) - mu1 * mu1).clamp_min(floor)
    p0, p1 = w0 / total, w1 / total
    tiny = torch.finfo(torch.float64).tiny
    crit = p0 * torch.log(v0) + p1 * torch.log(v1) - 2 * (p0 * torch.log(p0.clamp_min(tiny)) +
                                                          p1 * torch.log(p1.clamp_min(tiny)))
    crit = torch.where(valid, crit, torch.full_like(crit, float("inf")))
    k = int(torch.argmin(crit))
    return lo + (k + 1) * width


class _Valley(NamedTuple):
    cut: float  # the threshold
    depth: float  # smoothed density at the cut / the smaller of the two modes' densities (1: no valley)


def _valley(scores: torch.Tensor, bins: int, sigma_bins: float) -> _Valley:
    """The valley search of :func:`valley_threshold`, with how deep the valley is."""
    t_split = min_error_threshold(scores, bins=2 * bins)
    h = _histogram(scores, bins)
    if h.hist is None:
        return _Valley(h.hi, 1.0)
    hist, centres, lo, width = h.hist, h.centres, h.lo, h.width
    r = int(3 * sigma_bins) + 1
    x = torch.arange(-r, r + 1, dtype=torch.float64, device=hist.device)
    kernel = torch.exp(-0.5 * (x / sigma_bins) ** 2)
    dens = torch.nn.functional.conv1d(torch.nn.functional.pad(hist[None, None], (r, r)),
                                      (kernel / kernel.sum())[None, None])[0, 0]
    below = torch.nonzero(centres < t_split).reshape(-1)
    above = torch.nonzero(centres >= t_split).reshape(-1)
    if below.numel() == 0 or above.numel() == 0:
        return _Valley(t_split, 1.0)
    b = int(below[torch.argmax(dens[below])])
    a = int(above[torch.argmax(dens[above])])
    if a - b < 2:
        return _Valley(t_split, 1.0)
    seg = dens[b + 1:a]
    low = float(seg.min())
    is_min = (seg <= low + 1e-9 * max(1.0, low)).tolist()
    best_len, best_start, i = 0, 0, 0
    while i < len(is_min):
        if is_min[i]:
            j = i
            while j + 1 < len(is_min) and is_min[j + 1]:
                j += 1
            if j - i + 1 > best_len:
                best_len, best_start = j - i + 1, i
            i = j + 1
        else:
            i += 1
    k0, k1 = b + 1 + best_start, b + best_start + best_len
    depth = low / max(min(float(dens[a]), float(dens[b])), 1e-300)
    return _Valley(lo + ((k0 + k1) / 2 + 0.5) * width, min(depth, 1.0))


def valley_threshold(scores: torch.Tensor, bins: int = 256, sigma_bins: float = 2.0) -> float:
    """The middle of the widest lowest-density stretch between the two classes of ``scores`` [K].

    1. The minimum-error threshold (:func:`min_error_threshold`) splits the scores into a lower
       (background) and an upper (object) side.
    2. The score histogram (``bins`` bins over [min, max]) is smoothed with a Gaussian of
       ``sigma_bins`` bins; each side's mode is its densest bin.
    3. Between the two modes, the bins of minimal smoothed density are found; the cut is the centre
       of the longest run of them (the widest gap, so a maximal margin on both sides).

    Kittler-Illingworth alone survives small objects (where Otsu cuts inside the background) but
    can cut inside an object whose scores have a tail (Gaussians blended at its borders); the
    valley search keeps its split and moves the cut to the emptiest place between the classes.
    """
    return _valley(scores, bins, sigma_bins).cut


def top_cluster_threshold(scores: torch.Tensor, bins: int = 256, sigma_bins: float = 2.0,
                          max_depth: float = 0.35, min_fraction: float = 0.002, min_count: int = 32) -> float:
    """The automatic threshold: the valley below the highest-scoring cluster of ``scores`` [K].

    A scene's scores for one text usually form more than two clusters: the named object high, the
    other objects in the middle, and the largest surface (a table, a floor) lowest. Any two-class
    rule (Otsu, Kittler-Illingworth, :func:`valley_threshold`) splits off the largest cluster and
    selects everything else (all objects on the table for "potted plant"). This rule starts with
    :func:`valley_threshold` and then splits the upper side again, as long as

    * the new split has a real valley: the smoothed density at the cut is at most ``max_depth``
      times the lower of the two modes' densities (a single object's peak with a tail has no
      such valley, so the object is not cut into pieces), and
    * each side of the new split keeps at least ``min_fraction`` of all the scores and at least
      ``min_count`` scores (a few stray scores in the gap, or the sparse tail of a small object's
      peak, are not a cluster: their histogram is noise).

    Every split after the first uses the first one's bin width, so a tight peak is not stretched
    over the whole histogram and split at its noise.

    The last accepted cut is returned: the valley right below the top cluster.
    """
    s = scores.detach().reshape(-1).to(torch.float64)
    s = s[torch.isfinite(s)]
    if s.numel() == 0:
        raise ValueError("tiger.retrieval: no finite scores to threshold")
    v = _valley(s, bins, sigma_bins)
    cut = v.cut
    width = (float(s.max()) - float(s.min())) / bins  # every split sees the scores at this resolution
    min_count = max(int(min_fraction * s.numel()), int(min_count), 2)
    while True:
        upper = s[s > cut]
        if upper.numel() < 2 * min_count or width <= 0:
            return cut
        # the same bin width as the first split: a tight peak is not stretched over 256 bins
        sub_bins = int((float(upper.max()) - float(upper.min())) / width)
        if sub_bins < 8:
            return cut
        nxt = _valley(upper, sub_bins, sigma_bins)
        above = int((upper > nxt.cut).sum())
        if nxt.depth > max_depth or not nxt.cut > cut or min(above, upper.numel() - above) < min_count:
            return cut
        cut = nxt.cut


#: The threshold rules by name (``"auto"`` is :func:`top_cluster_threshold`).
TAU_RULES = {"auto": top_cluster_threshold, "valley": valley_threshold, "kittler": min_error_threshold,
             "otsu": otsu_threshold}


def choose_tau(scores: torch.Tensor, tau: Tau, score: str,
               temperature: float = DEFAULT_TEMPERATURE, margin: Optional[torch.Tensor] = None) -> float:
    """The selection threshold for ``scores`` [K].

    A number is used as given. ``None`` / ``"auto"``: :func:`top_cluster_threshold` (the valley
    below the highest-scoring cluster); ``"valley"``: :func:`valley_threshold` (two classes);
    ``"kittler"``: :func:`min_error_threshold`; ``"otsu"``: :func:`otsu_threshold`. For the LERF
    relevancy ``r = sigmoid(t m)`` the rule runs on the margin ``m`` (query cosine minus the
    hardest negative's: a cosine scale, where r itself saturates at 1 in float32): ``margin`` [K]
    when given (exact), else ``logit(r) / t``; the cut is mapped back through the sigmoid and is
    never below 0.5 (query no more similar than a negative).
    """
    rule = TAU_RULES.get("auto" if tau is None else tau) if (tau is None or isinstance(tau, str)) else None
    if rule is not None:
        if score != "relevancy":
            return rule(scores)
        if margin is None:
            r = scores.detach().to(torch.float64).clamp(1e-12, 1 - 1e-12)
            margin = torch.log(r / (1 - r)) / temperature
        t = float(torch.sigmoid(torch.tensor(rule(margin.detach().to(torch.float64)) * temperature,
                                             dtype=torch.float64)))
        return max(t, 0.5)
    if isinstance(tau, str):
        raise ValueError(f"tiger.retrieval: tau must be a number, 'auto', 'valley', 'kittler' or 'otsu', "
                         f"got '{tau}'")
    t = float(tau)
    if t != t:
        raise ValueError("tiger.retrieval: tau is NaN")
    return t


def _quantile(x: torch.Tensor, q: float) -> torch.Tensor:
    """Per-column linear-interpolated quantile of [K, C] (torch.quantile caps K at 2^24)."""
    xs = torch.sort(x, dim=0).values
    pos = q * (x.shape[0] - 1)
    i0 = int(pos)
    i1 = min(i0 + 1, x.shape[0] - 1)
    f = pos - i0
    return xs[i0] * (1 - f) + xs[i1] * f


def robust_bounds(points: torch.Tensor, quantiles: tuple[float, float] = (0.02, 0.98)
                  ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """(centre [3], lo [3], hi [3]) of points [K, 3], robust to stray Gaussians.

    The box spans the per-axis ``quantiles`` of the positions; the centre is the per-axis median.
    """
    ql, qh = quantiles
    if not 0.0 <= ql < qh <= 1.0:
        raise ValueError(f"tiger.retrieval: quantiles must satisfy 0 <= lo < hi <= 1, got {quantiles}")
    if points.dim() != 2 or points.shape[0] == 0:
        raise ValueError(f"tiger.retrieval: robust_bounds needs points [K>0, C], got {list(points.shape)}")
    p = points.detach().to(torch.float64)
    return _quantile(p, 0.5), _quantile(p, ql), _quantile(p, qh)


@dataclass
class Retrieval:
    """What a text query retrieved from a scene.

    Attributes:
        scores: [N] the score used for the selection (cosine or LERF relevancy), float32.
        cosine: [N] cosine similarity of each Gaussian's L with the projected query.
        relevancy: [N] LERF relevancy against the canonical negatives (None when not computed).
        mask: [N] bool, ``scores > tau``.
        tau: the threshold used.
        score: ``"cosine"`` or ``"relevancy"``.
        center: [3] median position of the selected Gaussians (None if nothing was selected).
        bbox_min, bbox_max: [3] per-axis quantile box of the selected positions (or None).
    """

    scores: torch.Tensor
    cosine: torch.Tensor
    relevancy: Optional[torch.Tensor]
    mask: torch.Tensor
    tau: float
    score: str
    center: Optional[torch.Tensor] = None
    bbox_min: Optional[torch.Tensor] = None
    bbox_max: Optional[torch.Tensor] = None

    @property
    def indices(self) -> torch.Tensor:
        """[K] indices of the selected Gaussians."""
        return torch.nonzero(self.mask).reshape(-1)

    @property
    def count(self) -> int:
        return int(self.mask.sum())

    def subscene(self, scene: GaussianScene) -> GaussianScene:
        """The selected Gaussians of ``scene`` as a scene of their own."""
        return scene.subset(self.mask)


def subset(scene: GaussianScene, mask: torch.Tensor) -> GaussianScene:
    """``scene.subset(mask)``: the Gaussians where ``mask`` [N] bool is True."""
    return scene.subset(mask)


def _features_of(scene: Union[GaussianScene, torch.Tensor]) -> tuple[torch.Tensor, Optional[torch.Tensor]]:
    if torch.is_tensor(scene):
        return scene, None
    if scene.lang is None:
        raise ValueError("tiger.retrieval: the scene has no language features (scene.lang is None): "
                         "train them with tiger.language.train_field")
    return scene.lang, scene.means


#: A Gaussian whose language feature is shorter than this fraction of the median norm carries no
#: language information (no training view saw it: the field left it at zero).
FEATURELESS_NORM = 0.1


def _informative(feats: torch.Tensor) -> torch.Tensor:
    """[N] bool: the Gaussians whose language feature [N, D] says something (norm at least
    :data:`FEATURELESS_NORM` times the median norm). Featureless Gaussians all score ~0 and would
    form a spike in the score histogram that the threshold rules take for a cluster; they are left
    out of the threshold's choice (and score below any cut above 0). All of them when fewer than
    two are informative."""
    norms = feats.detach().float().norm(dim=1)
    keep = norms >= FEATURELESS_NORM * norms.median()
    return keep if int(keep.sum()) >= 2 else torch.ones_like(keep)


def retrieve(scene: Union[GaussianScene, torch.Tensor], query: Query, *,
             encoder: Optional[TextEncoder] = None, pca: PCASource = None,
             negatives: Union[None, Sequence[str], torch.Tensor] = CANONICAL_NEGATIVES,
             score: str = "cosine", tau: Tau = "auto", temperature: float = DEFAULT_TEMPERATURE,
             quantiles: tuple[float, float] = (0.02, 0.98), check_finite: bool = True) -> Retrieval:
    """Retrieve the Gaussians matching one text query: ``O = {G : s > tau}`` (paper eq. 2).

    Args:
        scene: a scene with ``lang`` [N, D] (and ``means`` [N, 3] for the bounds; the PCA basis is
            read from ``lang_pca_basis``/``lang_pca_mean`` unless ``pca`` is given), or an [N, D]
            tensor of language features.
        query: a string (needs ``encoder``) or one embedding, [F] CLIP-space or [D] (see
            :func:`tiger.retrieval.text.embed_queries`).
        encoder: text encoder with ``encode_text(texts) -> [Q, F]``.
        pca: PCA (basis [F, D], mean [F]) when the scene does not carry it.
        negatives: canonical negatives for the LERF relevancy (strings or [M, F]/[M, D] embeddings);
            computed when they can be embedded, required for ``score="relevancy"``.
        score: ``"cosine"`` (the paper's s_i) or ``"relevancy"`` (LERF).
        tau: threshold, or a rule: ``"auto"`` (the valley below the top cluster),
            ``"valley"``, ``"kittler"``, ``"otsu"`` (see :func:`choose_tau`). Gaussians without a
            language feature (no training view saw them) are left out of a rule's choice.
        temperature: LERF softmax temperature.
        quantiles: per-axis quantiles of the selected positions for the bounding box.
    Returns:
        a :class:`Retrieval`.
    """
    if score not in ("cosine", "relevancy"):
        raise ValueError(f"tiger.retrieval: score must be 'cosine' or 'relevancy', got '{score}'")
    feats, means = _features_of(scene)
    if feats.dim() != 2:
        raise ValueError(f"tiger.retrieval: language features must be [N, D], got {list(feats.shape)}")
    d = feats.shape[1]
    pca_src = pca if pca is not None else (None if torch.is_tensor(scene) else scene)
    q = embed_queries(query, dim=d, encoder=encoder, pca=pca_src)
    if q.shape[0] != 1:
        raise ValueError(f"tiger.retrieval: retrieve takes one query, got {q.shape[0]} "
                         "(use tiger.retrieval.relevancy for batches)")
    neg = None
    can_embed_neg = negatives is not None and (encoder is not None or torch.is_tensor(negatives))
    if can_embed_neg:
        try:
            neg = embed_negatives(negatives, dim=d, encoder=encoder, pca=pca_src)
        except (KeyError, ValueError):
            if score == "relevancy":
                raise
            neg = None  # the cosine needs no negatives: a text table without them still answers
    elif score == "relevancy":
        raise ValueError("tiger.retrieval: score='relevancy' needs negatives: embeddings, or strings "
                         "with a text encoder")
    cos, rel = relevancy(feats.detach(), q, neg, temperature=temperature, check_finite=check_finite)
    cos = cos[:, 0]
    rel = rel[:, 0] if rel is not None else None
    s = rel if score == "relevancy" else cos
    keep = _informative(feats)
    margin = None
    if score == "relevancy":  # exact margins: the relevancy saturates at 1 in float32
        neg_cos, _ = relevancy(feats.detach(), neg, None, check_finite=False)
        margin = (cos.to(torch.float64) - neg_cos.to(torch.float64).amax(dim=1))[keep]
    t = choose_tau(s[keep], tau, score, temperature, margin=margin)
    mask = s > t
    out = Retrieval(scores=s, cosine=cos, relevancy=rel, mask=mask, tau=t, score=score)
    k = int(mask.sum())
    log.info("retrieval: %d of %d Gaussians with %s > %.4f", k, feats.shape[0], score, t)
    if k == 0:
        log.warning("retrieval: nothing selected (%s > %.4f); the query may not be in the scene", score, t)
    elif means is not None:
        out.center, out.bbox_min, out.bbox_max = robust_bounds(means.detach()[mask.to(means.device)], quantiles)
    return out
