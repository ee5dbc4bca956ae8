"""The public rasterization entry point: projection → (SH) → tile binning → compositing."""
from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple, Optional

import torch
from torch import Tensor

from tiger.ops.binning import BinningSettings, bin_gaussians
from tiger.ops.projection import project_gaussians
from tiger.ops.raster import RasterKernelSettings, rasterize
from tiger.ops.sh import sh_to_color

__all__ = ["rasterize_gaussians", "RasterSettings", "Projection", "project_for_raster",
           "composite", "composite_views", "bin_projection", "camera_center", "expected_depth", "sh_colors"]


@dataclass(frozen=True)
class RasterSettings:
    """The rasterizer's accuracy and speed keywords, with their defaults (SPEC §3); each is a
    keyword of :func:`rasterize_gaussians` (whose defaults are read from here). ``binning`` and
    ``kernels`` are the CUDA kernels' choices (same result; defaults: the measured best)."""

    near: float = 0.01
    far: float = 1e10
    eps2d: float = 0.3
    antialiased: bool = False
    alpha_max: float = 0.99
    alpha_threshold: float = 1.0 / 255.0
    t_min: float = 1e-4
    tile_size: int = 16
    check_finite: bool = True
    binning: BinningSettings = BinningSettings()
    kernels: RasterKernelSettings = RasterKernelSettings()


class Projection(NamedTuple):
    """One view's projected Gaussians, what :func:`composite` draws: means2d [N, 2] px, conics
    [N, 3], depths [N], opacities [N] (antialiasing applied), radii [N, 2] int32, features
    [N, C] (SH already evaluated), background [C] or None."""

    means2d: Tensor
    conics: Tensor
    depths: Tensor
    opacities: Tensor
    radii: Tensor
    features: Tensor
    background: Optional[Tensor]


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
    for (name, t), b in zip(named, bad):
        if b:
            count = int((~torch.isfinite(t)).sum())
            raise ValueError(f"{_NAME}: {name} contains {count} non-finite value(s) (NaN or Inf); "
                             "pass check_finite=False to skip this check")
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


def camera_center(viewmat: Tensor) -> Tensor:
    """Camera centre in world coordinates from a world→camera ``viewmat`` [4,4] → [3]."""
    R, t = viewmat[:3, :3], viewmat[:3, 3]
    return -(R.transpose(0, 1) @ t)


def sh_colors(means: Tensor, sh: Tensor, viewmat: Tensor, sh_degree: int,
              visible: Optional[Tensor] = None, sh_rest: Optional[Tensor] = None) -> Tensor:
    """[N, 3] RGB of each Gaussian seen from the camera of ``viewmat``: max(SH(dir) + 0.5, 0).

    The one SH→RGB step of the renderer (INRIA's convention), differentiable.

    Args:
        means: [N, 3] world-space centres.
        sh: [N, K, 3] coefficients (INRIA order, DC first), K >= (sh_degree + 1)^2.
        viewmat: [4, 4] world→camera (its centre gives each Gaussian's view direction).
        sh_degree: bands evaluated, 0..3.
        visible: [N] bool; rows that are False get colour max(0.5, 0) and no gradient.
        sh_rest: [N, K1, 3] or None: the coefficients are ``cat([sh, sh_rest], 1)``, read in
            place (a scene's DC band and higher bands; no [N, K, 3] copy on CUDA).
    """
    dirs = means - camera_center(viewmat.to(means))
    return torch.clamp_min(sh_to_color(dirs, sh, sh_degree, visible, sh_rest) + 0.5, 0.0)


def rasterize_gaussians(
    means: Tensor,
    quats: Tensor,
    scales: Tensor,
    opacities: Tensor,
    colors: Tensor,
    viewmat: Tensor,
    K: Tensor,
    width: int,
    height: int,
    *,
    background: Optional[Tensor] = None,
    sh_degree: Optional[int] = None,
    sh_rest: Optional[Tensor] = None,
    near: float = RasterSettings.near,
    far: float = RasterSettings.far,
    eps2d: float = RasterSettings.eps2d,
    antialiased: bool = RasterSettings.antialiased,
    alpha_max: float = RasterSettings.alpha_max,
    alpha_threshold: float = RasterSettings.alpha_threshold,
    t_min: float = RasterSettings.t_min,
    tile_size: int = RasterSettings.tile_size,
    check_finite: bool = RasterSettings.check_finite,
    binning: BinningSettings = BinningSettings(),
    kernels: RasterKernelSettings = RasterKernelSettings(),
) -> dict[str, Tensor]:
    """Render 3D Gaussians into one pinhole camera, differentiably.

    Args:
        means: [N, 3] world-space centres.
        quats: [N, 4] rotations (w, x, y, z); normalised inside (any non-zero norm).
        scales: [N, 3] standard deviations along the local axes (linear, world units).
        opacities: [N] in [0, 1].
        colors: [N, C] per-Gaussian channels (any C >= 1: RGB, 64-d language, both; with float32
            geometry they may be stored as float16/bfloat16, accumulated in float32), or with
            ``sh_degree=d`` spherical-harmonics coefficients [N, K, 3] with K >= (d+1)^2
            (INRIA order), evaluated per Gaussian for its view direction as max(SH + 0.5, 0).
        sh_rest: with ``sh_degree``, optional [N, K1, 3] higher-band coefficients: the SH input
            is then ``cat([colors, sh_rest], 1)`` (e.g. a scene's DC [N, 1, 3] and its rest),
            read in place on CUDA (float32) instead of copied.
        viewmat: [4, 4] world→camera transform, OpenCV axes (+x right, +y down, +z forward).
        K: [3, 3] pinhole intrinsics (fx, fy, cx, cy used; pixels).
        width, height: image size in pixels (whole numbers; 640.0 is accepted, 640.5 is not).
        background: [C] colour behind the Gaussians (default 0).
        near, far: camera-space depth range; Gaussians with centres outside are culled.
        eps2d: dilation added to the 2D covariance diagonal [px^2].
        antialiased: scale opacity by sqrt(det Σ2d / det(Σ2d + eps2d I)) (Mip-Splatting style).
        alpha_max: per-Gaussian alpha clamp (keeps 1 - alpha away from 0).
        alpha_threshold: contributions with alpha below are skipped (also the extent rule).
        t_min: a pixel stops compositing once transmittance would drop below this.
        tile_size: tile edge in pixels for binning.
        check_finite: input value checks (one reduction per input; off for speed): raise on
            NaN/Inf in any tensor, on a zero quaternion, an opacity outside [0, 1] or a negative
            scale, naming the tensor and its first bad row.
        binning: the CUDA binning's kernel choices (:class:`tiger.ops.binning.BinningSettings`;
            the tile lists are the same whichever runs).
        kernels: the CUDA compositing kernels' choices, forward and backward
            (:class:`tiger.ops.raster.RasterKernelSettings`; same result up to float32 rounding).

    Returns:
        dict with ``color`` [H, W, C], ``alpha`` [H, W], ``depth`` [H, W] (expected depth,
        Σ w z / Σ w, 0 where alpha == 0), ``depth_accum`` [H, W] (Σ w z), ``radii`` [N] int32
        (opacity-aware screen radius in px, 0 = culled), ``means2d`` [N, 2] (pixel centres; a
        non-leaf that can ``retain_grad()`` for densification), ``conics`` [N, 3],
        ``depths`` [N], ``n_isects`` (number of tile-Gaussian pairs, int).
        Every float output is differentiable w.r.t. every float input (viewmat and K included).
        When only ``colors``/``background`` require grad, the backward runs the features-only
        kernel (no geometry gradient is computed).
    """
    settings = RasterSettings(near=near, far=far, eps2d=eps2d, antialiased=antialiased,
                              alpha_max=alpha_max, alpha_threshold=alpha_threshold, t_min=t_min,
                              tile_size=tile_size, check_finite=check_finite, binning=binning,
                              kernels=kernels)
    p = project_for_raster(means, quats, scales, opacities, colors, viewmat, K, width, height,
                           background=background, sh_degree=sh_degree, sh_rest=sh_rest, settings=settings)
    return composite(p, width, height, settings)


def project_for_raster(means: Tensor, quats: Tensor, scales: Tensor, opacities: Tensor,
                       colors: Tensor, viewmat: Tensor, K: Tensor, width: int, height: int, *,
                       background: Optional[Tensor] = None, sh_degree: Optional[int] = None,
                       sh_rest: Optional[Tensor] = None,
                       settings: RasterSettings = RasterSettings()) -> Projection:
    """The first half of :func:`rasterize_gaussians` (same arguments, checked the same way):
    projection and the SH colour step. Batched renders project every view first, so that
    a tensor stacking the views' ``means2d`` can sit in the graph (see ``render_views``)."""
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
    if means.is_cuda and not 1 <= int(settings.tile_size) <= 16:
        raise ValueError(f"{_NAME}: the CUDA kernels take tile_size in [1, 16], got {settings.tile_size}")
    width, height = _check_size(width, height)
    channels = 3 if sh_degree is not None else colors.shape[1]
    if background is not None:
        _check_tensor(background, "background", (channels,), means)
        background = background.to(means.dtype)
    if settings.check_finite:
        _check_inputs({"means": means, "quats": quats, "scales": scales, "opacities": opacities,
                       "colors": colors, "sh_rest": sh_rest, "viewmat": viewmat, "K": K,
                       "background": background}, quats, scales, opacities)
    viewmat = viewmat.to(means.dtype)
    K = K.to(means.dtype)

    means2d, conics, depths, opac, radii = project_gaussians(
        means, quats, scales, opacities, viewmat, K, width, height, settings.eps2d, settings.near,
        settings.far, settings.alpha_threshold, settings.antialiased)

    if sh_degree is not None:
        feats = sh_colors(means, colors, viewmat, int(sh_degree), radii[:, 0] > 0, sh_rest)
    elif half_colors and not colors.is_cuda:
        feats = colors.float().contiguous()  # the CPU kernels accumulate in the storage dtype
    else:
        # CUDA reads float16/bfloat16 channels directly and accumulates in float32.
        feats = colors.contiguous()
    return Projection(means2d, conics, depths, opac, radii, feats, background)


def bin_projection(p: Projection, width: int, height: int,
                   settings: RasterSettings = RasterSettings()) -> tuple[Tensor, Tensor]:
    """Tile binning of a :class:`Projection`: (tile_offsets, gaussian_ids) of :func:`bin_gaussians`.
    On CUDA it reads the intersection count back (one host synchronisation)."""
    with torch.no_grad():
        return bin_gaussians(p.means2d, p.conics, p.opacities, p.depths, p.radii, int(width), int(height),
                             settings.tile_size, settings.alpha_threshold, settings.binning)


def expected_depth(depth_accum: Tensor, alpha: Tensor) -> Tensor:
    """Expected depth Σ w z / Σ w per pixel, 0 where ``alpha == 0``; differentiable.

    Shape: ``depth_accum`` and ``alpha`` [..., H, W] (the rasterizer's), the result the same.
    Where alpha == 0 no Gaussian contributed, so depth_accum is 0 there too: dividing by
    ``alpha + (alpha == 0)`` (1 there) gives that 0 exactly and no 0/0 in the backward, in three
    kernels (nested ``torch.where`` with scalars took six and more host time per render). The
    gradient reaching depth_accum at such pixels is read by no Gaussian (none contributes there).
    """
    return depth_accum / (alpha + (alpha == 0))


def composite(p: Projection, width: int, height: int,
              settings: RasterSettings = RasterSettings(),
              binned: Optional[tuple[Tensor, Tensor]] = None) -> dict[str, Tensor]:
    """The second half of :func:`rasterize_gaussians`: tile binning (unless ``binned`` gives
    :func:`bin_projection`'s result) and compositing of a :class:`Projection`; returns the
    rasterizer's dict."""
    width, height = int(width), int(height)
    means2d, conics, depths, opac, radii, feats, background = p
    tile_offsets, gaussian_ids = binned if binned is not None else bin_projection(p, width, height, settings)

    color, alpha, depth_accum, _, _ = rasterize(
        means2d, conics, opac, feats, depths, background, tile_offsets, gaussian_ids, width,
        height, settings.tile_size, settings.alpha_max, settings.alpha_threshold, settings.t_min,
        settings.kernels)
    depth = expected_depth(depth_accum, alpha)
    return {
        "color": color,
        "alpha": alpha,
        "depth": depth,
        "depth_accum": depth_accum,
        "radii": radii.amax(dim=1),
        "means2d": means2d,
        "conics": conics,
        "depths": depths,
        "n_isects": int(gaussian_ids.shape[0]),
    }


def composite_views(projections: list[Projection], width: int, height: int,
                    settings: RasterSettings = RasterSettings(),
                    means2d: Optional[Tensor] = None,
                    trainable: Optional[Tensor] = None) -> dict[str, Tensor]:
    """V views' :class:`Projection` s (of one scene of N Gaussians, one image size, one
    background) composited into stacked images: the second half of ``render_views``.

    The V views are binned and rasterized in one call each (``views=V``, CPU and CUDA: the V*N
    projected Gaussians, block v listed only in image v's tiles and evaluated at image v's own
    pixel coordinates), so view v is bit-identical to :func:`composite` of its projection (its
    gradients too on the CPU; on CUDA they are summed with atomics, equal up to rounding).
    On CUDA the binning reads its intersection count back once for all V views.

    Args:
        projections: V projections of the same N Gaussians (features [N, C] each).
        means2d: [V, N, 2] the stacked ``means2d`` of the projections to composite from (default:
            stacked here); a tensor in the caller's graph, so that its ``retain_grad()`` gives
            the per-view screen-space gradients.
        trainable: optional bool [N]: the Gaussians whose gradients the rasterizer's backward
            computes (the others, frozen, get zero screen-space and colour gradients and cost
            no gradient work; :func:`tiger.ops.raster.rasterize`'s ``trainable``, for every view).
    Returns:
        dict with 'color' [V, H, W, C], 'alpha', 'depth', 'depth_accum' [V, H, W], 'radii'
        [V, N] int32, 'means2d' [V, N, 2], 'conics' [V, N, 3], 'depths' [V, N], 'n_isects' [V]
        int64 (on the projections' device).
    """
    width, height = int(width), int(height)
    views = len(projections)
    if means2d is None:
        means2d = torch.stack([p.means2d for p in projections])
    n = means2d.shape[1]
    if trainable is not None:
        if not isinstance(trainable, Tensor) or trainable.dtype != torch.bool or trainable.shape != (n,):
            got = (f"{trainable.dtype} {list(trainable.shape)}" if isinstance(trainable, Tensor)
                   else type(trainable).__name__)
            raise ValueError(f"{_NAME}: trainable must be a bool tensor [N={n}], got {got}")
        trainable = trainable.to(means2d.device).repeat(views)  # the mask of every view's block
    flat = means2d.reshape(views * n, 2)
    conics = torch.cat([p.conics for p in projections])
    depths = torch.cat([p.depths for p in projections])
    opac = torch.cat([p.opacities for p in projections])
    radii = torch.cat([p.radii for p in projections])
    feats = torch.cat([p.features for p in projections])
    with torch.no_grad():
        tile_offsets, gaussian_ids = bin_gaussians(flat, conics, opac, depths, radii, width, height,
                                                   settings.tile_size, settings.alpha_threshold,
                                                   settings.binning, views=views)
    color, alpha, depth_accum, _, _ = rasterize(
        flat, conics, opac, feats, depths, projections[0].background, tile_offsets, gaussian_ids,
        width, height, settings.tile_size, settings.alpha_max, settings.alpha_threshold,
        settings.t_min, settings.kernels, views=views, trainable=trainable)
    color = color.reshape(views, height, width, -1)
    alpha = alpha.reshape(views, height, width)
    depth_accum = depth_accum.reshape(views, height, width)
    depth = expected_depth(depth_accum, alpha)
    view_tiles = (tile_offsets.shape[0] - 1) // views
    return {
        "color": color,
        "alpha": alpha,
        "depth": depth,
        "depth_accum": depth_accum,
        "radii": radii.amax(dim=1).reshape(views, n),
        "means2d": means2d,
        "conics": conics.reshape(views, n, 3),
        "depths": depths.reshape(views, n),
        "n_isects": tile_offsets[view_tiles::view_tiles] - tile_offsets[:-1:view_tiles],
    }
