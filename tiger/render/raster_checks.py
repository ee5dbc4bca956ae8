"""The input checks of :func:`tiger.rasterize_gaussians` (and of the batched renders built from its
halves): shapes, dtypes and devices of every tensor, the image size, and on request the values."""
from __future__ import annotations

from typing import Optional

import torch
from torch import Tensor

__all__ = ["checked_camera", "checked_sizes", "checked_trainable"]

_NAME = "tiger.rasterize_gaussians"


def _check_tensor(t: object, name: str, shape: tuple, ref: Optional[Tensor] = None) -> Tensor:
    if not isinstance(t, Tensor):
        raise TypeError(f"{_NAME}: {name} must be a torch.Tensor, got {type(t).__name__}")
    ok = t.dim() == len(shape) and all(s is None or t.shape[i] == s for i, s in enumerate(shape))
    if not ok:
        want = "[" + ", ".join("*" if s is None else str(s) for s in shape) + "]"
        raise ValueError(f"{_NAME}: {name} must have shape {want}, got {list(t.shape)}")
    if not t.is_floating_point():
        raise TypeError(f"{_NAME}: {name} must be a floating-point tensor, got {t.dtype}")
    if ref is not None and t.device != ref.device:
        raise ValueError(f"{_NAME}: {name} is on {t.device} but means is on {ref.device}")
    return t


def _raise_nonfinite(named: list[tuple[str, Tensor]], bad: list[bool]) -> None:
    """The error for the first of ``named`` whose flag in ``bad`` is set, counting its NaN/Inf."""
    for (name, t), b in zip(named, bad):
        if b:
            count = int((~torch.isfinite(t)).sum())
            raise ValueError(f"{_NAME}: {name} contains {count} non-finite value(s) (NaN or Inf); "
                             "pass check_finite=False to skip this check")


def _check_inputs(tensors: dict[str, Optional[Tensor]], quats: Tensor, scales: Tensor,
                  opacities: Tensor) -> None:
    """check_finite's tests, read back in one device synchronisation (was one per tensor):
    NaN/Inf in any tensor, then zero quaternions (no rotation), negative scales and opacities
    outside [0, 1] -- input mistakes the kernels would render without complaint. The message
    names the tensor (and its first bad row); the details are looked up only on failure."""
    named = [(name, t) for name, t in tensors.items() if t is not None]
    with torch.no_grad():
        zero_q = (quats == 0).all(dim=1)
        neg_s = (scales < 0).any(dim=1)
        bad_o = (opacities < 0) | (opacities > 1)
        flags = [~torch.isfinite(t).all() for _, t in named] + [zero_q.any(), bad_o.any(), neg_s.any()]
        bad = torch.stack(flags).tolist()
    _raise_nonfinite(named, bad)
    hint = "; pass check_finite=False to skip the input checks"
    for b, (name, rows_bad, t, what) in zip(bad[len(named):], (
            ("quats", zero_q, quats, "is zero, not a rotation"),
            ("opacities", bad_o, opacities, "is outside [0, 1]"),
            ("scales", neg_s, scales, "has a negative entry (scales are linear standard "
                                      "deviations, not logs)"))):
        if b:
            rows = rows_bad.nonzero().flatten()
            row = int(rows[0])
            raise ValueError(f"{_NAME}: {name}[{row}] = {t[row].tolist()} {what} "
                             f"({rows.numel()} bad row(s) of {t.shape[0]}){hint}")


def _check_size(width: object, height: object) -> tuple[int, int]:
    out = []
    for name, v in (("width", width), ("height", height)):
        if isinstance(v, Tensor) and v.numel() == 1:
            v = v.item()
        if isinstance(v, bool) or not (isinstance(v, int) or hasattr(v, "__index__")
                                       or (isinstance(v, float) and v.is_integer())):
            raise TypeError(f"{_NAME}: {name} must be a whole number of pixels, got {v!r}")
        out.append(int(v))
    if out[0] <= 0 or out[1] <= 0:
        raise ValueError(f"{_NAME}: width and height must be positive, got {out[0]}x{out[1]}")
    return out[0], out[1]


def checked_sizes(means: Tensor, quats: Tensor, scales: Tensor, opacities: Tensor, colors: Tensor,
                   viewmat: Tensor, K: Tensor, width: int, height: int, background: Optional[Tensor],
                   sh_degree: Optional[int], sh_rest: Optional[Tensor], tile_size: int,
                   check_finite: bool) -> tuple[int, int, Optional[Tensor]]:
    """The checks of :func:`tiger.rasterize_gaussians`' inputs (one clear error naming the tensor and
    what is wrong); returns the image size as ints and the background in the geometry's dtype.
    ``check_finite``: also the value checks (NaN/Inf, zero quaternions, negative scales, opacities
    outside [0, 1]; one device synchronisation)."""
    _check_tensor(means, "means", (None, 3))
    n = means.shape[0]
    if means.dtype not in (torch.float32, torch.float64):
        raise TypeError(f"{_NAME}: means must be float32 or float64, got {means.dtype}")
    _check_tensor(quats, "quats", (n, 4), means)
    _check_tensor(scales, "scales", (n, 3), means)
    _check_tensor(opacities, "opacities", (n,), means)
    if sh_degree is None:
        if sh_rest is not None:
            raise ValueError(f"{_NAME}: sh_rest needs sh_degree (it is part of the SH coefficients)")
        _check_tensor(colors, "colors", (n, None), means)
        if colors.shape[1] < 1:
            raise ValueError(f"{_NAME}: colors must have at least one channel, got shape "
                             f"{list(colors.shape)}")
    else:
        if not 0 <= int(sh_degree) <= 3:
            raise ValueError(f"{_NAME}: sh_degree must be in [0, 3], got {sh_degree}")
        _check_tensor(colors, "colors (SH coefficients)", (n, None, 3), means)
        k = colors.shape[1]
        if sh_rest is not None:
            _check_tensor(sh_rest, "sh_rest", (n, None, 3), means)
            if sh_rest.dtype != colors.dtype:
                raise TypeError(f"{_NAME}: sh_rest has dtype {sh_rest.dtype} but colors has {colors.dtype}")
            k += sh_rest.shape[1]
        if k < (sh_degree + 1) ** 2:
            raise ValueError(f"{_NAME}: colors{' + sh_rest' if sh_rest is not None else ''} hold {k} SH "
                             f"coefficients per Gaussian but sh_degree={sh_degree} needs {(sh_degree + 1) ** 2}")
    _check_tensor(viewmat, "viewmat", (4, 4), means)
    _check_tensor(K, "K", (3, 3), means)
    for name, t in (("quats", quats), ("scales", scales), ("opacities", opacities)):
        if t.dtype != means.dtype:
            raise TypeError(f"{_NAME}: {name} has dtype {t.dtype} but means has {means.dtype}")
    half_colors = (sh_degree is None and means.dtype == torch.float32
                   and colors.dtype in (torch.float16, torch.bfloat16))
    if colors.dtype != means.dtype and not half_colors:
        raise TypeError(f"{_NAME}: colors has dtype {colors.dtype} but means has {means.dtype} "
                        "(float16/bfloat16 colors are accepted with float32 geometry)")
    if means.is_cuda and not 1 <= int(tile_size) <= 16:
        raise ValueError(f"{_NAME}: the CUDA kernels take tile_size in [1, 16], got {tile_size}")
    width, height = _check_size(width, height)
    channels = 3 if sh_degree is not None else colors.shape[1]
    if background is not None:
        _check_tensor(background, "background", (channels,), means)
        background = background.to(means.dtype)
    if check_finite:
        _check_inputs({"means": means, "quats": quats, "scales": scales, "opacities": opacities,
                       "colors": colors, "sh_rest": sh_rest, "viewmat": viewmat, "K": K,
                       "background": background}, quats, scales, opacities)
    return width, height, background


def checked_trainable(trainable: Optional[Tensor], n: int, device: torch.device) -> Optional[Tensor]:
    """A render's ``trainable`` mask on ``device`` (None stays None); anything but a bool tensor
    [N] is one error naming what was given."""
    if trainable is None:
        return None
    if not isinstance(trainable, Tensor) or trainable.dtype != torch.bool or trainable.shape != (n,):
        got = (f"{trainable.dtype} {list(trainable.shape)}" if isinstance(trainable, Tensor)
               else type(trainable).__name__)
        raise ValueError(f"{_NAME}: trainable must be a bool tensor [N={n}], got {got}")
    return trainable.to(device)



def checked_camera(viewmat: Tensor, K: Tensor, means: Tensor, check_finite: bool,
                   colors: Optional[Tensor] = None) -> None:
    """The per-view part of :func:`checked_sizes` for a further view of a render whose first view
    went through it (same scene, size and settings): ``viewmat`` [4, 4] and ``K`` [3, 3] beside
    ``means``, and with ``check_finite`` their values and those of the view's own ``colors`` (when
    given, [N, C] like the first view's), in one device synchronisation. The scene's tensors are
    not read again."""
    _check_tensor(viewmat, "viewmat", (4, 4), means)
    _check_tensor(K, "K", (3, 3), means)
    if colors is not None:
        _check_tensor(colors, "colors", (means.shape[0], None), means)
    if check_finite:
        named = [(name, t) for name, t in (("colors", colors), ("viewmat", viewmat), ("K", K)) if t is not None]
        with torch.no_grad():
            bad = torch.stack([~torch.isfinite(t).all() for _, t in named]).tolist()
        _raise_nonfinite(named, bad)
