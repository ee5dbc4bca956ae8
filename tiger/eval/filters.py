"""Image filters of the LERF/LangSplat localization protocol, written to match OpenCV exactly.

``mean_filter`` is ``cv2.filter2D(x, -1, ones((k, k)) / k^2)``: anchor at ``k // 2`` (so an even
kernel covers rows ``y - k//2 .. y + k - 1 - k//2``) and BORDER_REFLECT_101 borders. The box sums
are taken in 64-bit fixed point through cumulative sums, so they are exact: pixels whose windows
hold the same values get bit-identical results, and the ties of the arg-max are real ties.
"""
from __future__ import annotations

import torch

_FIXED_BITS = 40  # |x| <= 1 maps to <= 2^40; window sums of 10^6 pixels stay far below 2^63


def reflect101_index(n: int, before: int, after: int, device: torch.device | None = None) -> torch.Tensor:
    """Source indices of a length-``n`` axis padded by ``before``/``after`` with BORDER_REFLECT_101
    (``gfedcb|abcdefgh|gfedcba``), repeated as often as needed (OpenCV's rule for any pad size)."""
    i = torch.arange(-before, n + after, device=device)
    if n == 1:
        return torch.zeros_like(i)
    period = 2 * (n - 1)
    i = torch.remainder(i, period)
    return torch.where(i >= n, period - i, i)


def _box_sum_axis(x: torch.Tensor, k: int, dim: int) -> torch.Tensor:
    n = x.shape[dim]
    a = k // 2
    idx = reflect101_index(n, a, k - 1 - a, x.device)
    p = x.index_select(dim, idx)
    c = torch.cumsum(p, dim=dim)
    zero = torch.zeros_like(c.narrow(dim, 0, 1))
    c = torch.cat([zero, c], dim=dim)
    return c.narrow(dim, k, n) - c.narrow(dim, 0, n)


def box_sum_fixed(x: torch.Tensor, size: int) -> tuple[torch.Tensor, float]:
    """Exact ``size x size`` window sums of ``x`` [..., H, W] in int64 fixed point.

    Returns (sums [..., H, W] int64, scale): ``sums / scale`` are the real sums of the values
    rounded to the fixed-point grid (relative resolution 2^-40 of max |x|).
    """
    if size < 1:
        raise ValueError(f"tiger.eval: filter size must be >= 1, got {size}")
    if x.dim() < 2:
        raise ValueError(f"tiger.eval: the map must be [..., H, W], got {list(x.shape)}")
    xd = x.detach().to(torch.float64)
    if not bool(torch.isfinite(xd).all()):
        raise ValueError("tiger.eval: the relevancy map has NaN or Inf values")
    peak = float(xd.abs().max()) if xd.numel() else 0.0
    scale = float(2 ** _FIXED_BITS) / peak if peak > 0 else 1.0
    q = torch.round(xd * scale).to(torch.int64)
    s = _box_sum_axis(_box_sum_axis(q, size, x.dim() - 1), size, x.dim() - 2)
    return s, scale


def mean_filter(x: torch.Tensor, size: int = 30) -> torch.Tensor:
    """``cv2.filter2D(x, -1, ones((size, size)) / size**2)`` on [..., H, W]; float64 result."""
    s, scale = box_sum_fixed(x, size)
    return s.to(torch.float64) / (scale * size * size)


def argmax_points(x: torch.Tensor, size: int = 30) -> tuple[torch.Tensor, torch.Tensor]:
    """All maxima of the ``size`` mean-filtered map [H, W]: ((x, y) pixel coordinates [P, 2] int64,
    the filtered map [H, W] float64). Ties are exact (see the module docstring)."""
    if x.dim() != 2:
        raise ValueError(f"tiger.eval: a relevancy map must be [H, W], got {list(x.shape)}")
    s, scale = box_sum_fixed(x, size)
    ys, xs = torch.nonzero(s == s.max(), as_tuple=True)
    return torch.stack([xs, ys], dim=1), s.to(torch.float64) / (scale * size * size)


def majority_smooth(mask: torch.Tensor, radius: int = 3) -> torch.Tensor:
    """LangSplat's ``smooth``: each pixel takes the majority value (ties -> 0) of the window
    ``rows [max(0, i - r), min(i + r + 1, H - 1))`` x the same for columns, the reference's
    exclusive ``H - 1`` upper bound included. Pixels whose window is empty keep their value."""
    if mask.dim() != 2:
        raise ValueError(f"tiger.eval: mask must be [H, W], got {list(mask.shape)}")
    h, w = mask.shape
    m = mask.to(torch.int64)
    ii = torch.zeros(h + 1, w + 1, dtype=torch.int64, device=mask.device)
    ii[1:, 1:] = m.cumsum(0).cumsum(1)
    r = torch.arange(h, device=mask.device)
    c = torch.arange(w, device=mask.device)
    r0, r1 = (r - radius).clamp_min(0), (r + radius + 1).clamp_max(h - 1)
    c0, c1 = (c - radius).clamp_min(0), (c + radius + 1).clamp_max(w - 1)
    r1 = torch.maximum(r1, r0)
    c1 = torch.maximum(c1, c0)
    ones = (ii[r1][:, c1] - ii[r0][:, c1] - ii[r1][:, c0] + ii[r0][:, c0])
    total = (r1 - r0)[:, None] * (c1 - c0)[None, :]
    out = (2 * ones > total)
    return torch.where(total > 0, out, mask.bool())
