"""The public rasterization entry point: projection → (SH) → tile binning → compositing."""
from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple, Optional, Sequence, Union

import torch
from torch import Tensor

from tiger.ops.binning import BinningSettings, bin_gaussians
from tiger.ops.projection import project_gaussians
from tiger.ops.raster import RasterKernelSettings, rasterize
from tiger.ops.render import render_forward
from tiger.ops.sh import sh_to_color

from .raster_checks import checked_camera, checked_sizes, checked_trainable

__all__ = ["rasterize_gaussians", "RasterSettings", "Projection", "project_for_raster", "project_views",
           "composite", "composite_views", "bin_projection", "camera_center", "expected_depth", "sh_colors",
           "sh_colors_views"]

#: V cameras' matrices: a tensor [V, r, c] or a sequence of V tensors [r, c] (e.g. each camera's own).
ViewMatrices = Union[Tensor, Sequence[Tensor]]


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


def camera_center(viewmat: Tensor) -> Tensor:
    """Camera centre in world coordinates from a world→camera ``viewmat`` [4,4] → [3]."""
    R, t = viewmat[:3, :3], viewmat[:3, 3]
    return -(R.transpose(0, 1) @ t)


def _stack_views(ts: Sequence[Tensor]) -> Tensor:
    """``torch.stack(ts)``; one view's is a view of it, no copy (the one-view render's path)."""
    return ts[0][None] if len(ts) == 1 else torch.stack(list(ts))


def _unstack_views(t: Tensor) -> list[Tensor]:
    """``t.unbind(0)``; one view's is ``t.squeeze(0)``, whose backward is a view too (an unbind's
    stacks the gradients: a copy)."""
    return [t.squeeze(0)] if t.shape[0] == 1 else list(t.unbind(0))


def sh_colors_views(means: Tensor, sh: Tensor, viewmats: ViewMatrices, sh_degree: int,
                    visible: Optional[Tensor] = None, sh_rest: Optional[Tensor] = None,
                    trainable: Optional[Tensor] = None) -> Tensor:
    """[V, N, 3] RGB of each Gaussian seen from each of V cameras, max(SH(dir) + 0.5, 0), in one
    SH call (:func:`tiger.ops.sh.sh_to_color` with directions [V, N, 3]).

    The one SH→RGB step of the renderer (INRIA's convention), differentiable. The call reads each
    coefficient row once for all V views, and its backward sums the views' coefficient gradients
    in the kernel (one ``sh`` / ``sh_rest`` gradient, not V of them added by autograd). View v
    equals ``sh_colors(means, sh, viewmats[v], ...)`` bit for bit.

    Args:
        means: [N, 3] world-space centres.
        sh: [N, K, 3] coefficients (INRIA order, DC first), K >= (sh_degree + 1)^2.
        viewmats: V world→camera matrices, [V, 4, 4] or a sequence of V [4, 4] (their centres
            give each Gaussian's view direction per view).
        sh_degree: bands evaluated, 0..3.
        visible: [V, N] bool; (view, row) pairs that are False get colour max(0.5, 0) and no
            gradient.
        sh_rest: [N, K1, 3] or None: the coefficients are ``cat([sh, sh_rest], 1)``, read in
            place (a scene's DC band and higher bands; no [N, K, 3] copy on CUDA).
        trainable: [N] bool or None: the rows whose gradients the backward computes (the others
            get zero gradients and cost no gradient work: :func:`tiger.ops.sh.sh_to_color`).
    """
    # Each centre by camera_center's own 3x3 product, one per view: a batched product may round
    # differently, and view v must match the one-view render (and tiger::render_forward, which
    # takes the same product) bit for bit. V tiny products; the SH op is the costly part.
    centres = _stack_views([camera_center(vm.to(means)) for vm in viewmats])  # [V, 3]
    dirs = means[None] - centres[:, None]  # [V, N, 3]
    return torch.clamp_min(sh_to_color(dirs, sh, sh_degree, visible, sh_rest, trainable=trainable) + 0.5, 0.0)


def sh_colors(means: Tensor, sh: Tensor, viewmat: Tensor, sh_degree: int,
              visible: Optional[Tensor] = None, sh_rest: Optional[Tensor] = None,
              trainable: Optional[Tensor] = None) -> Tensor:
    """[N, 3] RGB of each Gaussian seen from the camera of ``viewmat``: max(SH(dir) + 0.5, 0).

    The one-view case of :func:`sh_colors_views` (the renderer's SH→RGB step), differentiable.

    Args:
        means: [N, 3] world-space centres.
        sh: [N, K, 3] coefficients (INRIA order, DC first), K >= (sh_degree + 1)^2.
        viewmat: [4, 4] world→camera (its centre gives each Gaussian's view direction).
        sh_degree: bands evaluated, 0..3.
        visible: [N] bool; rows that are False get colour max(0.5, 0) and no gradient.
        sh_rest: [N, K1, 3] or None: the coefficients are ``cat([sh, sh_rest], 1)``, read in
            place (a scene's DC band and higher bands; no [N, K, 3] copy on CUDA).
        trainable: [N] bool or None: the rows whose gradients the backward computes (the others
            get zero gradients and cost no gradient work: :func:`tiger.ops.sh.sh_to_color`).
    """
    vis = None if visible is None else visible[None]
    return sh_colors_views(means, sh, [viewmat], sh_degree, vis, sh_rest, trainable).squeeze(0)


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
        kernel (no geometry gradient is computed). A render that autograd does not record
        (``torch.no_grad()``, or no input requiring grad) runs as one op,
        :func:`tiger.ops.render.render_forward` (the same kernels in C++, the same values).
    """
    settings = RasterSettings(near=near, far=far, eps2d=eps2d, antialiased=antialiased,
                              alpha_max=alpha_max, alpha_threshold=alpha_threshold, t_min=t_min,
                              tile_size=tile_size, check_finite=check_finite, binning=binning,
                              kernels=kernels)
    inputs = (means, quats, scales, opacities, colors, sh_rest, viewmat, K, background)
    if not _records_gradients(inputs):
        width, height, background = checked_sizes(means, quats, scales, opacities, colors, viewmat, K, width, height,
                                                  background, sh_degree, sh_rest, settings.tile_size,
                                                  settings.check_finite)
        return _render_without_gradients(means, quats, scales, opacities, colors, viewmat, K, width, height,
                                          background, sh_degree, sh_rest, settings)
    p = project_for_raster(means, quats, scales, opacities, colors, viewmat, K, width, height,
                           background=background, sh_degree=sh_degree, sh_rest=sh_rest, settings=settings)
    return composite(p, width, height, settings)


def _records_gradients(tensors: tuple) -> bool:
    """Whether autograd records this render (or a transform or the compiler traces it): then it
    runs op by op, each op with its autograd formula."""
    if torch.compiler.is_compiling() or torch._C._are_functorch_transforms_active():
        return True
    return torch.is_grad_enabled() and any(t is not None and t.requires_grad for t in tensors)


def _render_without_gradients(means: Tensor, quats: Tensor, scales: Tensor, opacities: Tensor,
                              colors: Tensor, viewmat: Tensor, K: Tensor, width: int, height: int,
                              background: Optional[Tensor], sh_degree: Optional[int],
                              sh_rest: Optional[Tensor], settings: RasterSettings) -> dict[str, Tensor]:
    """:func:`rasterize_gaussians`' dict from one ``tiger::render_forward`` call (checked inputs):
    projection, SH, binning and compositing chained in C++, no Python between the stages."""
    s = settings
    color, alpha, depth, depth_accum, radii, means2d, conics, depths, ids = render_forward(
        means, quats, scales, opacities, colors, sh_rest, sh_degree, background, viewmat, K, width, height,
        s.eps2d, s.near, s.far, s.alpha_threshold, s.antialiased, s.tile_size, s.alpha_max, s.t_min,
        s.binning, s.kernels)
    return {"color": color, "alpha": alpha, "depth": depth, "depth_accum": depth_accum, "radii": radii,
            "means2d": means2d, "conics": conics, "depths": depths, "n_isects": int(ids.shape[0])}


def project_for_raster(means: Tensor, quats: Tensor, scales: Tensor, opacities: Tensor,
                       colors: Tensor, viewmat: Tensor, K: Tensor, width: int, height: int, *,
                       background: Optional[Tensor] = None, sh_degree: Optional[int] = None,
                       sh_rest: Optional[Tensor] = None,
                       settings: RasterSettings = RasterSettings(),
                       trainable: Optional[Tensor] = None) -> Projection:
    """The first half of :func:`rasterize_gaussians` (same arguments, checked the same way):
    projection and the SH colour step; the one-view case of :func:`project_views`.
    ``trainable`` ([N] bool): the rows whose projection and SH gradients the backward computes
    (:func:`tiger.ops.projection.project_gaussians`, :func:`sh_colors`)."""
    return project_views(means, quats, scales, opacities, colors, [viewmat], [K], width, height,
                         background=background, sh_degree=sh_degree, sh_rest=sh_rest, settings=settings,
                         trainable=trainable)[0]


def project_views(means: Tensor, quats: Tensor, scales: Tensor, opacities: Tensor,
                  colors: Tensor, viewmats: ViewMatrices, Ks: ViewMatrices, width: int, height: int, *,
                  background: Optional[Tensor] = None, sh_degree: Optional[int] = None,
                  sh_rest: Optional[Tensor] = None,
                  settings: RasterSettings = RasterSettings(),
                  trainable: Optional[Tensor] = None) -> list[Projection]:
    """The first half of a render of V views of one image size: each view's projection (one call
    per view) and the SH colours of all V views in one call (:func:`sh_colors_views`). Batched
    renders project every view first, so that a tensor stacking the views' ``means2d`` can sit in
    the graph (see ``render_views``, :func:`composite_views`).

    Args:
        means, quats, scales, opacities, width, height, background, sh_degree, sh_rest, settings:
            as :func:`rasterize_gaussians` (checked the same way: the scene's tensors once, each
            view's camera and own colours per view).
        colors: as :func:`rasterize_gaussians`' (SH coefficients [N, K, 3] with ``sh_degree``,
            or channels [N, C] shared by the views), or without ``sh_degree`` [V, N, C]: each
            view's own channels (e.g. its SH colour in front of shared features).
        viewmats: V world→camera matrices, [V, 4, 4] or a sequence of V [4, 4].
        Ks: V intrinsics, [V, 3, 3] or a sequence of V [3, 3].
        trainable: [N] bool or None: the rows whose projection and SH gradients the backward
            computes (:func:`tiger.ops.projection.project_gaussians`, :func:`sh_colors_views`).
    Returns:
        V :class:`Projection` s; view v equals ``project_for_raster`` of camera v bit for bit.
    """
    viewmats, Ks = list(viewmats), list(Ks)
    views = len(viewmats)
    if views == 0 or len(Ks) != views:
        raise ValueError(f"tiger.project_views: needs V >= 1 viewmats and as many Ks, got {views} viewmats "
                         f"and {len(Ks)} Ks")
    per_view_colors = sh_degree is None and isinstance(colors, Tensor) and colors.dim() == 3
    if per_view_colors and colors.shape[0] != views:
        raise ValueError(f"tiger.project_views: per-view colors must have shape [V={views}, N, C], got "
                         f"{list(colors.shape)}")
    geometry = []
    for v in range(views):
        view_colors = colors[v] if per_view_colors else colors
        if v == 0:  # the scene's tensors, size and background once; each further view its camera
            width, height, bg = checked_sizes(means, quats, scales, opacities, view_colors, viewmats[v], Ks[v],
                                              width, height, background, sh_degree, sh_rest, settings.tile_size,
                                              settings.check_finite)
        else:
            checked_camera(viewmats[v], Ks[v], means, settings.check_finite,
                           view_colors if per_view_colors else None)
        viewmats[v], Ks[v] = viewmats[v].to(means.dtype), Ks[v].to(means.dtype)
        geometry.append(project_gaussians(
            means, quats, scales, opacities, viewmats[v], Ks[v], width, height, settings.eps2d, settings.near,
            settings.far, settings.alpha_threshold, settings.antialiased, trainable))

    if sh_degree is not None:
        visible = _stack_views([g[4] for g in geometry])[..., 0] > 0  # [V, N]: radii > 0, culled otherwise
        feats = _unstack_views(sh_colors_views(means, colors, viewmats, int(sh_degree), visible, sh_rest,
                                               trainable))
    else:
        if colors.dtype != means.dtype and not colors.is_cuda:  # float16/bfloat16 channels (checked)
            shared = colors.float().contiguous()  # the CPU kernels accumulate in the storage dtype
        else:
            # CUDA reads float16/bfloat16 channels directly and accumulates in float32.
            shared = colors.contiguous()
        feats = _unstack_views(shared) if per_view_colors else [shared] * views
    return [Projection(*g, f, bg) for g, f in zip(geometry, feats)]


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
    trainable = checked_trainable(trainable, n, means2d.device)
    if trainable is not None:
        trainable = trainable.repeat(views)  # the mask of every view's block
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
