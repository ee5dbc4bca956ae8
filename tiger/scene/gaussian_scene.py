"""The Gaussian scene: the one container every stage of TIGER reads and writes."""
from __future__ import annotations

import copy
import math
import os
from typing import Any, Iterable, Iterator, Literal, NamedTuple, Optional, Sequence, Union

import torch

from tiger.ops.binning import BinningSettings
from tiger.ops.raster import RasterKernelSettings
from tiger.render import Camera
from tiger.render.raster_checks import checked_trainable
from tiger.render.rasterize import (Projection, RasterSettings, composite_views, project_views,
                                   rasterize_gaussians, sh_colors, sh_colors_views)

from .ply import read_ply_state, write_ply_state
from .sh import MAX_SH_DEGREE, num_sh_bases, rgb_to_sh, sh_degree_from_rest, sh_to_rgb

PathLike = Union[str, os.PathLike]
#: What :meth:`GaussianScene.render` draws: SH colour (None/"rgb"), language features, both,
#: any per-Gaussian channels [N, C], or the SH colour followed by such channels (("rgb", [N, C])).
ColorSpec = Union[None, Literal["rgb", "lang", "rgb+lang"], torch.Tensor, tuple[Literal["rgb"], torch.Tensor]]
#: A rasterizer keyword's value (near, far, eps2d, antialiased, tile_size, check_finite, ...).
RasterOption = Union[float, int, bool, BinningSettings, RasterKernelSettings]

#: Per-Gaussian tensors, in the order used by optimizers and files.
PARAM_NAMES = ("means", "log_scales", "quats", "opacity_logits", "sh_dc", "sh_rest", "lang")

#: INRIA's learning rates (position before scaling by the scene extent).
DEFAULT_LRS = {
    "means": 1.6e-4,
    "log_scales": 5e-3,
    "quats": 1e-3,
    "opacity_logits": 5e-2,
    "sh_dc": 2.5e-3,
    "sh_rest": 2.5e-3 / 20.0,
    "lang": 2.5e-3,
}


def inverse_sigmoid(x: torch.Tensor) -> torch.Tensor:
    """logit(x), with x clamped away from 0 and 1 so it stays finite."""
    eps = 1e-6 if x.dtype == torch.float32 else 1e-12
    x = x.clamp(eps, 1 - eps)
    return torch.log(x / (1 - x))


class GaussianScene:
    """A set of N anisotropic 3D Gaussians with SH colour and optional language features.

    Stored (optimised) parameters, all on one device and of one floating dtype:
        means           [N, 3]   world positions
        log_scales      [N, 3]   log of the standard deviations along the local axes
        quats           [N, 4]   rotations (w, x, y, z); normalised at use
        opacity_logits  [N]      logit of the opacity
        sh_dc           [N, 3]   degree-0 SH coefficient per RGB channel
        sh_rest         [N, K, 3] higher SH bands, K = (d+1)^2 - 1 for degree d (INRIA order)
        lang            [N, D] or None   language embeddings (D = 64 in TIGER)
    Not optimised:
        lang_pca_basis  [F, D] or None   projects F-dim CLIP features to D: (f - mean) @ basis
        lang_pca_mean   [F] or None
        metadata        dict of JSON-serialisable values (saved in PLY comments / checkpoints)
    """

    def __init__(self, means: torch.Tensor, log_scales: torch.Tensor, quats: torch.Tensor,
                 opacity_logits: torch.Tensor, sh_dc: torch.Tensor,
                 sh_rest: Optional[torch.Tensor] = None, lang: Optional[torch.Tensor] = None,
                 lang_pca_basis: Optional[torch.Tensor] = None,
                 lang_pca_mean: Optional[torch.Tensor] = None,
                 metadata: Optional[dict] = None) -> None:
        if sh_rest is None:
            sh_rest = means.new_zeros((means.shape[0], 0, 3))
        self.means, self.log_scales, self.quats = means, log_scales, quats
        self.opacity_logits, self.sh_dc, self.sh_rest = opacity_logits, sh_dc, sh_rest
        self.lang = lang
        self.lang_pca_basis, self.lang_pca_mean = lang_pca_basis, lang_pca_mean
        self.metadata: dict = dict(metadata or {})
        self.validate()

    # -- construction -------------------------------------------------------------------
    @classmethod
    def from_points(cls, points: torch.Tensor, colors: Optional[torch.Tensor] = None,
                    sh_degree: int = 3, opacity: float = 0.1,
                    scales: Optional[torch.Tensor] = None) -> "GaussianScene":
        """INRIA's initialisation from a point cloud.

        Args:
            points: [P, 3] positions.
            colors: [P, 3] RGB in [0, 1] (default mid grey).
            sh_degree: SH degree of the scene (higher bands start at zero).
            opacity: initial opacity of every Gaussian.
            scales: [P] isotropic standard deviations; default: the root mean squared
                distance to the 3 nearest neighbours (as INRIA's ``distCUDA2``).
        """
        if points.ndim != 2 or points.shape[1] != 3 or points.shape[0] == 0:
            raise ValueError(f"tiger: from_points needs points [P>0, 3], got {list(points.shape)}")
        points = points.detach().float() if not points.is_floating_point() else points.detach()
        P = points.shape[0]
        if colors is None:
            colors = torch.full_like(points, 0.5)
        if colors.shape != points.shape:
            raise ValueError(f"tiger: from_points: colors must be [P, 3] = {list(points.shape)}, "
                             f"got {list(colors.shape)}")
        if scales is None:
            scales = knn_mean_distance(points, k=3).clamp_min(1e-7)
        log_s = torch.log(scales.to(points)).unsqueeze(1).repeat(1, 3)
        quats = points.new_zeros((P, 4))
        quats[:, 0] = 1
        op = inverse_sigmoid(torch.full((P,), float(opacity), dtype=points.dtype, device=points.device))
        sh_dc = rgb_to_sh(colors.to(points))
        sh_rest = points.new_zeros((P, num_sh_bases(sh_degree) - 1, 3))
        return cls(points.clone(), log_s, quats, op, sh_dc, sh_rest)

    @classmethod
    def from_values(cls, means: torch.Tensor, quats: torch.Tensor, scales: torch.Tensor,
                    opacities: torch.Tensor, rgb: torch.Tensor, lang: Optional[torch.Tensor] = None,
                    metadata: Optional[dict] = None) -> "GaussianScene":
        """A degree-0 scene from rendered values rather than stored parameters.

        Args:
            means: [N, 3]; quats: [N, 4] (w, x, y, z); scales: [N, 3] linear standard deviations
                (> 0); opacities: [N] in (0, 1); rgb: [N, 3] colours in [0, 1];
            lang: [N, D] language embeddings or None.
        The stored parameters are log(scales), logit(opacities) and rgb_to_sh(rgb).
        """
        if not bool((scales > 0).all()):
            raise ValueError("tiger: GaussianScene.from_values needs scales > 0")
        return cls(means, torch.log(scales), quats, inverse_sigmoid(opacities), rgb_to_sh(rgb),
                   lang=lang, metadata=metadata)

    @classmethod
    def random_in_box(cls, n: int, lo: Sequence[float], hi: Sequence[float], sh_degree: int = 3,
                      generator: Optional[torch.Generator] = None,
                      dtype: torch.dtype = torch.float32) -> "GaussianScene":
        """``n`` Gaussians uniform in the box [lo, hi] with random colours (INRIA's
        initialisation for scenes without a point cloud)."""
        lo_t = torch.as_tensor(lo, dtype=dtype)
        hi_t = torch.as_tensor(hi, dtype=dtype)
        if lo_t.shape != (3,) or hi_t.shape != (3,) or not bool((hi_t > lo_t).all()):
            raise ValueError(f"tiger: random_in_box needs lo < hi, both [3]; got {lo}, {hi}")
        pts = lo_t + (hi_t - lo_t) * torch.rand((n, 3), generator=generator, dtype=dtype)
        cols = torch.rand((n, 3), generator=generator, dtype=dtype)
        return cls.from_points(pts, cols, sh_degree=sh_degree)

    # -- checks and properties ------------------------------------------------------------
    def validate(self) -> None:
        """Check shapes, dtypes and devices; raise ValueError naming the tensor."""
        N = self.means.shape[0] if self.means.ndim == 2 else -1
        expect = {
            "means": (N, 3), "log_scales": (N, 3), "quats": (N, 4), "opacity_logits": (N,),
            "sh_dc": (N, 3),
        }
        if self.means.ndim != 2 or self.means.shape[1] != 3:
            raise ValueError(f"tiger: GaussianScene.means must be [N, 3], got {list(self.means.shape)}")
        if not self.means.is_floating_point():
            raise ValueError(f"tiger: GaussianScene.means must be floating point, got {self.means.dtype}")
        for name, shape in expect.items():
            t = getattr(self, name)
            if not isinstance(t, torch.Tensor) or tuple(t.shape) != shape:
                got = list(t.shape) if isinstance(t, torch.Tensor) else type(t).__name__
                raise ValueError(f"tiger: GaussianScene.{name} must be {list(shape)}, got {got}")
        r = self.sh_rest
        if r.ndim != 3 or r.shape[0] != N or r.shape[2] != 3:
            raise ValueError(f"tiger: GaussianScene.sh_rest must be [N={N}, K, 3], got {list(r.shape)}")
        try:
            sh_degree_from_rest(r.shape[1])
        except ValueError as exc:
            raise ValueError(f"tiger: GaussianScene.sh_rest {list(r.shape)}: {exc}") from None
        if self.lang is not None and (self.lang.ndim != 2 or self.lang.shape[0] != N):
            raise ValueError(f"tiger: GaussianScene.lang must be [N={N}, D], got {list(self.lang.shape)}")
        if (self.lang_pca_basis is None) != (self.lang_pca_mean is None):
            raise ValueError("tiger: GaussianScene.lang_pca_basis and lang_pca_mean come together")
        if self.lang_pca_basis is not None:
            b, m = self.lang_pca_basis, self.lang_pca_mean
            if b.ndim != 2 or m.ndim != 1 or m.shape[0] != b.shape[0]:
                raise ValueError(f"tiger: GaussianScene.lang_pca_basis [F, D] and lang_pca_mean [F] "
                                 f"disagree: {list(b.shape)} vs {list(m.shape)}")
            if self.lang is not None and b.shape[1] != self.lang.shape[1]:
                raise ValueError(f"tiger: GaussianScene.lang_pca_basis maps to {b.shape[1]} dims but "
                                 f"lang has {self.lang.shape[1]}")
        for name in PARAM_NAMES:
            t = getattr(self, name)
            if t is None:
                continue
            if t.dtype != self.means.dtype or t.device != self.means.device:
                raise ValueError(f"tiger: GaussianScene.{name} is {t.dtype} on {t.device} but means is "
                                 f"{self.means.dtype} on {self.means.device}")

    def __len__(self) -> int:
        return self.means.shape[0]

    @property
    def num_gaussians(self) -> int:
        return self.means.shape[0]

    @property
    def sh_degree(self) -> int:
        return sh_degree_from_rest(self.sh_rest.shape[1])

    @property
    def device(self) -> torch.device:
        return self.means.device

    @property
    def dtype(self) -> torch.dtype:
        return self.means.dtype

    @property
    def scales(self) -> torch.Tensor:
        """[N, 3] standard deviations (exp of log_scales)."""
        return torch.exp(self.log_scales)

    @property
    def opacities(self) -> torch.Tensor:
        """[N] opacities in (0, 1)."""
        return torch.sigmoid(self.opacity_logits)

    @property
    def sh(self) -> torch.Tensor:
        """[N, (d+1)^2, 3] all SH coefficients (DC first), the rasterizer's colour input."""
        return torch.cat([self.sh_dc.unsqueeze(1), self.sh_rest], dim=1)

    @property
    def rgb(self) -> torch.Tensor:
        """[N, 3] view-independent colour of the DC band, clamped at 0 like the renderer."""
        return sh_to_rgb(self.sh_dc).clamp_min(0)

    def params(self) -> dict[str, torch.Tensor]:
        """The optimisable tensors by name (``lang`` only when present)."""
        return {n: getattr(self, n) for n in PARAM_NAMES if getattr(self, n) is not None}

    # -- copies -------------------------------------------------------------------------
    def _map(self, fn, pca_fn=None) -> "GaussianScene":
        pca_fn = pca_fn or (lambda t: t)
        kw = {n: (None if getattr(self, n) is None else fn(getattr(self, n))) for n in PARAM_NAMES}
        for n in ("lang_pca_basis", "lang_pca_mean"):
            t = getattr(self, n)
            kw[n] = None if t is None else pca_fn(t)
        return GaussianScene(**kw, metadata=copy.deepcopy(self.metadata))

    def to(self, device: Optional[Union[torch.device, str]] = None,
           dtype: Optional[torch.dtype] = None) -> "GaussianScene":
        """Copy (or self-sharing view) on ``device`` with floating ``dtype``; PCA data
        follows the device (and the dtype)."""
        return self._map(lambda t: t.to(device=device, dtype=dtype),
                         lambda t: t.to(device=device, dtype=dtype))

    def detach(self) -> "GaussianScene":
        """Same values, no autograd history, ``requires_grad`` off (storage shared)."""
        return self._map(lambda t: t.detach())

    def clone(self) -> "GaussianScene":
        """Independent copy (detached)."""
        return self._map(lambda t: t.detach().clone(), lambda t: t.clone())

    def subset(self, mask: torch.Tensor) -> "GaussianScene":
        """The Gaussians selected by ``mask``: a [N] bool mask or a 1-D index tensor."""
        mask = torch.as_tensor(mask, device=self.device)
        if mask.dtype == torch.bool:
            if mask.shape != (len(self),):
                raise ValueError(f"tiger: subset mask must be [N={len(self)}] bool, got {list(mask.shape)}")
        elif mask.dtype in (torch.int64, torch.int32, torch.int16, torch.int8, torch.uint8):
            if mask.ndim != 1:
                raise ValueError(f"tiger: subset indices must be 1-D, got {list(mask.shape)}")
            mask = mask.long()
            if mask.numel() and (int(mask.min()) < -len(self) or int(mask.max()) >= len(self)):
                raise ValueError(f"tiger: subset index out of range for {len(self)} Gaussians")
        else:
            raise ValueError(f"tiger: subset takes a bool mask or integer indices, got {mask.dtype}")
        return self._map(lambda t: t.detach()[mask], lambda t: t.clone())

    @staticmethod
    def concat(scenes: Sequence["GaussianScene"]) -> "GaussianScene":
        """All Gaussians of ``scenes`` in order. Lower SH degrees are padded with zero
        bands; language features must be present in all or none (PCA data is taken from
        the first scene and must agree across scenes). Metadata of the first scene is kept."""
        scenes = list(scenes)
        if not scenes:
            raise ValueError("tiger: concat needs at least one scene")
        ref = scenes[0]
        degree = max(s.sh_degree for s in scenes)
        K = num_sh_bases(degree) - 1
        has_lang = [s.lang is not None for s in scenes]
        if any(has_lang) and not all(has_lang):
            raise ValueError("tiger: concat: some scenes have language features and some do not")
        for i, s in enumerate(scenes):
            if s.device != ref.device or s.dtype != ref.dtype:
                raise ValueError(f"tiger: concat: scene {i} is {s.dtype} on {s.device}, scene 0 is "
                                 f"{ref.dtype} on {ref.device}")
            if (s.lang_pca_basis is None) != (ref.lang_pca_basis is None) or (
                    s.lang_pca_basis is not None
                    and not (torch.equal(s.lang_pca_basis, ref.lang_pca_basis)
                             and torch.equal(s.lang_pca_mean, ref.lang_pca_mean))):
                raise ValueError(f"tiger: concat: scene {i} has a different language PCA basis")

        def pad(r: torch.Tensor) -> torch.Tensor:
            return torch.cat([r, r.new_zeros((r.shape[0], K - r.shape[1], 3))], 1)

        kw = {n: torch.cat([getattr(s, n).detach() for s in scenes]) for n in PARAM_NAMES
              if n not in ("sh_rest", "lang")}
        kw["sh_rest"] = torch.cat([pad(s.sh_rest.detach()) for s in scenes])
        kw["lang"] = torch.cat([s.lang.detach() for s in scenes]) if all(has_lang) else None
        return GaussianScene(**kw, lang_pca_basis=ref.lang_pca_basis, lang_pca_mean=ref.lang_pca_mean,
                             metadata=copy.deepcopy(ref.metadata))

    def with_sh_degree(self, degree: int) -> "GaussianScene":
        """Copy truncated or zero-padded to SH ``degree``."""
        K = num_sh_bases(degree) - 1
        r = self.sh_rest.detach()
        r = r[:, :K] if r.shape[1] >= K else torch.cat([r, r.new_zeros((len(self), K - r.shape[1], 3))], 1)
        out = self.clone()
        out.sh_rest = r.clone()
        return out

    def equal(self, other: "GaussianScene") -> bool:
        """Bit-exact equality of every tensor (and of metadata)."""
        for n in PARAM_NAMES + ("lang_pca_basis", "lang_pca_mean"):
            a, b = getattr(self, n), getattr(other, n)
            if (a is None) != (b is None):
                return False
            if a is not None and (a.shape != b.shape or a.dtype != b.dtype or not torch.equal(a, b)):
                return False
        return self.metadata == other.metadata

    # -- optimisation -------------------------------------------------------------------
    def parameter_groups(self, lrs: Optional[dict[str, float]] = None,
                         names: Optional[Iterable[str]] = None) -> list[dict[str, Any]]:
        """Turn the stored tensors into leaf tensors that require grad and return one
        optimizer group per parameter: ``[{"params": [t], "lr": lr, "name": name}, ...]``.

        Args:
            lrs: learning rate by name; missing names use :data:`DEFAULT_LRS`.
            names: which parameters to optimise (default: all present); the others get
                ``requires_grad=False``.
        """
        lrs = {**DEFAULT_LRS, **(lrs or {})}
        names = list(self.params()) if names is None else list(names)
        for n in names:
            if n not in PARAM_NAMES or getattr(self, n) is None:
                raise ValueError(f"tiger: parameter_groups: no parameter named '{n}' in this scene")
        groups = []
        for n in PARAM_NAMES:
            t = getattr(self, n)
            if t is None:
                continue
            t = t.detach().requires_grad_(n in names)
            setattr(self, n, t)
            if n in names:
                groups.append({"params": [t], "lr": float(lrs[n]), "name": n})
        return groups

    # -- rendering ----------------------------------------------------------------------
    def render(self, camera: Camera, colors: ColorSpec = None, *,
               background: Optional[torch.Tensor] = None, sh_degree: Optional[int] = None,
               **options: RasterOption) -> dict[str, torch.Tensor]:
        """Render the scene from ``camera`` with :func:`tiger.rasterize_gaussians`.

        Args:
            camera: the view (its viewmat and K are cast to the scene's dtype/device).
            colors: what each Gaussian carries into the image:
                ``None`` or ``"rgb"``: its SH colour for this view ([H, W, 3]);
                ``"lang"``: its language embedding ([H, W, D]);
                ``"rgb+lang"``: both in one pass ([H, W, 3 + D]);
                a tensor [N, C]: any per-Gaussian channels (gradients flow into it);
                ``("rgb", tensor [N, C])``: the SH colour and those channels in one pass ([H, W, 3 + C]).
            background: [C] colour behind the Gaussians (default zeros).
            sh_degree: SH bands used for the colour (default: all of the scene's).
            **options: rasterizer keywords (near, far, eps2d, antialiased, check_finite, ...).
        Returns:
            the rasterizer's dict: 'color' [H, W, C], 'alpha' [H, W], 'depth' [H, W],
            'depth_accum' [H, W], 'radii' [N], 'means2d' [N, 2], 'conics' [N, 3], 'depths' [N],
            'n_isects' (int). Differentiable w.r.t. the scene's tensors and a ``colors`` tensor.
        """
        _settings(options)  # unknown keywords: one error naming them
        c = _color_inputs(self, colors, sh_degree)
        cam = camera.to(device=self.device, dtype=self.dtype)
        feats, raster_deg, rest = _view_colors(self, c, [cam.viewmat])
        if c.per_view_rgb:
            feats = feats.squeeze(0)  # [1, N, 3 + C] -> this view's [N, 3 + C]
        # a render autograd does not record runs as one op (tiger::render_forward)
        return rasterize_gaussians(self.means, self.quats, self.scales, self.opacities, feats, cam.viewmat, cam.K,
                                   cam.width, cam.height, background=background, sh_degree=raster_deg, sh_rest=rest,
                                   **options)

    def view_colors(self, camera: Camera, sh_degree: Optional[int] = None) -> torch.Tensor:
        """[N, 3] RGB of each Gaussian seen from ``camera``: max(SH(dir) + 0.5, 0), the
        rasterizer's own SH step (:func:`tiger.render.sh_colors`, differentiable)."""
        deg = self._check_sh_degree(sh_degree)
        return sh_colors(self.means, self.sh[:, : num_sh_bases(deg)],
                         camera.viewmat.to(self.means), deg)

    def _check_sh_degree(self, sh_degree: Optional[int]) -> int:
        deg = self.sh_degree if sh_degree is None else int(sh_degree)
        if not 0 <= deg <= self.sh_degree:
            raise ValueError(f"tiger: render sh_degree must be in 0..{self.sh_degree}, got {deg}")
        return deg

    # -- files ----------------------------------------------------------------------------
    @classmethod
    def load_ply(cls, path: PathLike, allow_nonfinite: bool = False,
                 dtype: torch.dtype = torch.float32) -> "GaussianScene":
        """Read a 3DGS PLY (INRIA, gsplat, nerfstudio, SuperSplat... exports; see
        :func:`tiger.scene.ply.read_ply_state`): ``lang`` when ``lang_*`` properties exist, PCA
        data from the sidecar ``<stem>.lang_pca.npz``, metadata from the header comment.

        Raises:
            SceneFormatError naming the file and the missing or malformed property.
        """
        return cls.from_state_dict(read_ply_state(path, allow_nonfinite=allow_nonfinite, dtype=dtype))

    def save_ply(self, path: PathLike, include_language: bool = True,
                 include_metadata: bool = True) -> None:
        """Write an INRIA-layout binary PLY (float32), atomically (see
        :func:`tiger.scene.ply.write_ply_state`); ``include_language=False`` leaves out
        ``lang_*`` for viewers that need INRIA's exact vertex size."""
        write_ply_state(self.detach().to("cpu", torch.float32).state_dict(), path,
                        include_language=include_language, include_metadata=include_metadata)

    def state_dict(self) -> dict[str, Any]:
        """Plain dict of tensors + metadata (for checkpoints)."""
        d = {n: getattr(self, n) for n in PARAM_NAMES + ("lang_pca_basis", "lang_pca_mean")}
        d = {k: (None if v is None else v.detach()) for k, v in d.items()}
        d["metadata"] = copy.deepcopy(self.metadata)
        return d

    @classmethod
    def from_state_dict(cls, d: dict[str, Any]) -> "GaussianScene":
        missing = [n for n in ("means", "log_scales", "quats", "opacity_logits", "sh_dc") if n not in d]
        if missing:
            raise ValueError(f"tiger: scene state dict lacks {missing}")
        kw = {n: d.get(n) for n in PARAM_NAMES + ("lang_pca_basis", "lang_pca_mean")}
        return cls(**kw, metadata=d.get("metadata") or {})

    def __repr__(self) -> str:
        lang = f", lang={self.lang.shape[1]}" if self.lang is not None else ""
        return (f"GaussianScene(N={len(self)}, sh_degree={self.sh_degree}{lang}, "
                f"dtype={self.dtype}, device={self.device})")


def render_views(scene: GaussianScene, cameras: Sequence[Camera], colors: ColorSpec = None, *,
                 background: Optional[torch.Tensor] = None, sh_degree: Optional[int] = None,
                 trainable: Optional[torch.Tensor] = None,
                 **options: RasterOption) -> dict[str, torch.Tensor]:
    """Render ``scene`` from V cameras of one image size; the outputs are stacked.

    ``colors``, ``background``, ``sh_degree`` and ``options`` are those of
    :meth:`GaussianScene.render` (one ``colors`` tensor [N, C] serves every view). The scene's
    activations (scales, opacities) are computed once for all views, so gradients of a loss
    over the V renders reach the scene's tensors and ``colors`` through one graph. Each view is
    projected by its own call, the SH colours of all V views come from one call (its backward
    sums the views' SH gradients in the kernel: :func:`tiger.render.rasterize.project_views`);
    the V views are then binned and rasterized in one call each, on the CPU and on CUDA
    (:func:`tiger.render.rasterize.composite_views`). ``trainable``: optional
    bool [N]: the Gaussians whose gradients the rasterizer's, the projection's and the SH colours'
    backward compute (an edit's editable ones); the frozen ones get zero gradients and cost no
    gradient work there.

    Returns:
        dict with 'color' [V, H, W, C], 'alpha' [V, H, W], 'depth' [V, H, W],
        'depth_accum' [V, H, W], 'radii' [V, N] int32, 'means2d' [V, N, 2] (``retain_grad()``
        gives the per-view screen-space gradients), 'conics' [V, N, 3], 'depths' [V, N],
        'n_isects' [V] int64. View v equals ``scene.render(cameras[v], ...)``.
    """
    cameras = list(cameras)
    if not cameras:
        raise ValueError("tiger: render_views needs at least one camera")
    size = (cameras[0].width, cameras[0].height)
    for i, cam in enumerate(cameras):
        if (cam.width, cam.height) != size:
            raise ValueError(f"tiger: render_views stacks views of one size: camera {i} "
                             f"('{cam.image_name}') is {cam.width}x{cam.height}, camera 0 is "
                             f"{size[0]}x{size[1]}")
    projections = _project_each(scene, cameras, colors, background, sh_degree, options, trainable)
    # Composite from one stacked means2d, so that its retain_grad() sees every view.
    means2d = torch.stack([p.means2d for p in projections])
    return composite_views(projections, size[0], size[1], _settings(options), means2d, trainable)


#: Views rendered together by :func:`render_view_chunks` and :func:`render_rgb` (bounds the stacked
#: per-view projections).
RGB_VIEWS_PER_PASS = 8


def render_view_chunks(scene: GaussianScene, cameras: Sequence[Camera], colors: ColorSpec = None, *,
                       views_per_pass: int = RGB_VIEWS_PER_PASS,
                       **options: Any) -> Iterator[tuple[int, dict[str, torch.Tensor]]]:
    """:func:`render_views` over any number of cameras of any sizes: consecutive cameras of one
    image size, at most ``views_per_pass`` at a time, each chunk in one set of launches.

    ``colors`` and ``options`` (``background``, ``sh_degree``, rasterizer keywords) are
    :func:`render_views`'. Yields ``(first, outputs)``: the index of the chunk's first camera in
    ``cameras`` and :func:`render_views`' stacked outputs for its views (view v of the chunk
    equals ``scene.render(cameras[first + v], ...)``). The pictures of ``tiger render``,
    turntables and grids (:func:`render_rgb`) come through here.
    """
    if views_per_pass < 1:
        raise ValueError(f"tiger: render_view_chunks needs views_per_pass >= 1, got {views_per_pass}")
    cameras = list(cameras)
    start = 0
    while start < len(cameras):
        size = (cameras[start].width, cameras[start].height)
        stop = start + 1
        while (stop < len(cameras) and stop - start < views_per_pass
               and (cameras[stop].width, cameras[stop].height) == size):
            stop += 1
        yield start, render_views(scene, cameras[start:stop], colors, **options)
        start = stop


@torch.no_grad()
def render_rgb(scene: GaussianScene, cameras: Sequence[Camera], background: Union[None, torch.Tensor,
               Sequence[float]] = None, *, footprint: Optional[torch.Tensor] = None
               ) -> Union[torch.Tensor, tuple[torch.Tensor, torch.Tensor]]:
    """RGB pictures of ``scene`` (its full SH colour, clamped to [0, 1], no gradients) from V
    cameras of one size: the one helper for turntables, before/after grids, metrics, guidance
    targets and an edit's original renders (:func:`render_views`, :data:`RGB_VIEWS_PER_PASS`
    views at a time).

    Args:
        cameras: V cameras of one image size (cast to the scene's device and dtype).
        background: [3] colour behind the Gaussians (a tensor or 3 numbers; default black).
        footprint: optional [N] bool or float weights in [0, 1]: also render each pixel's
            opacity-weighted share of these Gaussians (in the same pass, background 0).
    Returns:
        [V, H, W, 3] on the scene's device, or ``(rgb, footprint [V, H, W] in [0, 1])``.
    """
    cameras = list(cameras)
    bg = torch.zeros(3) if background is None else torch.as_tensor(background)
    bg = bg.to(scene.device, scene.dtype).reshape(-1)
    if bg.shape != (3,):
        raise ValueError(f"tiger: render_rgb background must be 3 numbers, got shape {list(bg.shape)}")
    colors: ColorSpec = "rgb"
    if footprint is not None:
        if footprint.shape != (len(scene),):
            raise ValueError(f"tiger: render_rgb footprint must be [N={len(scene)}], got {list(footprint.shape)}")
        colors = ("rgb", footprint.to(scene.device, scene.dtype)[:, None])
        bg = torch.cat([bg, bg.new_zeros(1)])
    sizes = {(cam.width, cam.height) for cam in cameras}
    if len(sizes) > 1:
        raise ValueError(f"tiger: render_rgb stacks views of one size, got {sorted(sizes)}")
    frozen = scene.detach()
    parts = [r["color"].clamp(0, 1) for _, r in render_view_chunks(frozen, cameras, colors, background=bg,
                                                                   check_finite=False)]
    out = torch.cat(parts) if parts else render_views(frozen, cameras, colors)["color"]  # no camera: its error
    return out if footprint is None else (out[..., :3], out[..., 3])


def _settings(options: dict[str, RasterOption]) -> RasterSettings:
    try:
        return RasterSettings(**options)
    except TypeError:
        known = sorted(RasterSettings.__dataclass_fields__)
        raise TypeError(f"tiger: render got unknown rasterizer keyword(s) {sorted(set(options) - set(known))}; "
                        f"known: {known}") from None


class _ColorInputs(NamedTuple):
    """A render's colour input resolved against a scene: ``feats`` (per-Gaussian channels [N, C],
    or the SH DC band [N, 1, 3] when ``sh_degree`` is set: the rasterizer evaluates SH then),
    ``sh_rest`` (the higher bands, read in place), ``degree`` (the scene's SH bands used) and
    ``per_view_rgb`` (each view's SH colour goes in front of ``feats``)."""

    feats: torch.Tensor
    sh_degree: Optional[int]
    sh_dc: torch.Tensor
    sh_rest: Optional[torch.Tensor]
    degree: int
    per_view_rgb: bool


def _color_inputs(scene: GaussianScene, colors: ColorSpec, sh_degree: Optional[int]) -> _ColorInputs:
    deg = scene._check_sh_degree(sh_degree)
    n = len(scene)
    raster_deg: Optional[int] = None
    per_view_rgb = False
    # DC and higher bands as they are stored (the SH op reads both; no [N, K, 3] cat per render)
    sh_dc = scene.sh_dc[:, None]
    sh_rest = scene.sh_rest[:, : num_sh_bases(deg) - 1] if deg > 0 else None
    if colors is None or (isinstance(colors, str) and colors == "rgb"):
        feats, raster_deg = sh_dc, deg
    elif isinstance(colors, str) and colors in ("lang", "rgb+lang"):
        if scene.lang is None:
            raise ValueError(f"tiger: render(colors='{colors}'): the scene has no language features")
        feats, per_view_rgb = scene.lang, colors == "rgb+lang"
    elif isinstance(colors, torch.Tensor) or (isinstance(colors, tuple) and len(colors) == 2
                                              and isinstance(colors[0], str) and colors[0] == "rgb"
                                              and isinstance(colors[1], torch.Tensor)):
        feats = colors if isinstance(colors, torch.Tensor) else colors[1]
        if feats.dim() != 2 or feats.shape[0] != n:
            raise ValueError(f"tiger: render colors must be a per-Gaussian tensor [N={n}, C], got "
                             f"{list(feats.shape)}")
        per_view_rgb = isinstance(colors, tuple)
    else:
        raise ValueError("tiger: render colors must be None, 'rgb', 'lang', 'rgb+lang', a tensor [N, C] or "
                         f"('rgb', tensor [N, C]), got {colors!r}")
    return _ColorInputs(feats, raster_deg, sh_dc, sh_rest, deg, per_view_rgb)


def _view_colors(scene: GaussianScene, c: _ColorInputs, viewmats: Sequence[torch.Tensor],
                 trainable: Optional[torch.Tensor] = None) -> tuple[torch.Tensor, Optional[int], Optional[torch.Tensor]]:
    """V views' ``colors``, ``sh_degree`` and ``sh_rest`` arguments of the rasterizer
    (:func:`tiger.render.rasterize.project_views`; ``viewmats``: V [4, 4] in the scene's dtype):
    shared by the views (channels [N, C], or the SH DC band with its degree: the projection
    evaluates SH then), or with ``per_view_rgb`` each view's SH colour in front of ``feats``,
    [V, N, 3 + C], from one SH call for the V views."""
    if not c.per_view_rgb:
        return c.feats, c.sh_degree, c.sh_rest if c.sh_degree is not None else None
    rgb = sh_colors_views(scene.means, c.sh_dc, viewmats, c.degree, sh_rest=c.sh_rest, trainable=trainable)
    return torch.cat([rgb, c.feats.expand(len(viewmats), -1, -1)], 2), None, None


def _project_each(scene: GaussianScene, cameras: Sequence[Camera], colors: ColorSpec,
                  background: Optional[torch.Tensor], sh_degree: Optional[int],
                  options: dict[str, RasterOption], trainable: Optional[torch.Tensor] = None) -> list[Projection]:
    """Each camera's projection, sharing the activated geometry and the colour input, and the SH
    colours of all the cameras in one call (:func:`tiger.render.rasterize.project_views`); the
    projection's and the SH colours' backward walk only the ``trainable`` rows when given ([N] bool)."""
    settings = _settings(options)
    c = _color_inputs(scene, colors, sh_degree)
    n = len(scene)
    means, quats, scales, opacities = scene.means, scene.quats, scene.scales, scene.opacities
    trainable = checked_trainable(trainable, n, scene.device)
    cams = [camera.to(device=scene.device, dtype=scene.dtype) for camera in cameras]
    viewmats = [cam.viewmat for cam in cams]
    feats, raster_deg, rest = _view_colors(scene, c, viewmats, trainable)
    return project_views(means, quats, scales, opacities, feats, viewmats, [cam.K for cam in cams],
                         cams[0].width, cams[0].height, background=background, sh_degree=raster_deg, sh_rest=rest,
                         settings=settings, trainable=trainable)


def read_ply(path: PathLike, allow_nonfinite: bool = False,
             dtype: torch.dtype = torch.float32) -> GaussianScene:
    """:meth:`GaussianScene.load_ply` as a function."""
    return GaussianScene.load_ply(path, allow_nonfinite=allow_nonfinite, dtype=dtype)


def write_ply(scene: GaussianScene, path: PathLike, include_language: bool = True,
              include_metadata: bool = True) -> None:
    """:meth:`GaussianScene.save_ply` as a function."""
    scene.save_ply(path, include_language=include_language, include_metadata=include_metadata)


def knn_mean_distance(points: torch.Tensor, k: int = 3, chunk: int = 4096) -> torch.Tensor:
    """[P] root of the mean squared distance of each point to its k nearest others.

    Exact, chunked O(P^2) on the points' device (P up to a few 10^5 on a GPU); uses
    scipy's KD-tree on CPU when available (much faster for large clouds).
    """
    P = points.shape[0]
    if P <= 1:
        return points.new_ones((P,))
    k = min(k, P - 1)
    if points.device.type == "cpu" and P > 20000:
        try:
            from scipy.spatial import cKDTree

            d, _ = cKDTree(points.double().numpy()).query(points.double().numpy(), k=k + 1)
            return torch.from_numpy((d[:, 1:] ** 2).mean(1) ** 0.5).to(points.dtype)
        except ImportError:
            pass
    out = []
    for s in range(0, P, chunk):
        d2 = torch.cdist(points[s:s + chunk].double(), points.double()).square()
        d2[torch.arange(d2.shape[0]), torch.arange(s, s + d2.shape[0])] = math.inf
        out.append(d2.topk(k, dim=1, largest=False).values.mean(1).sqrt())
    return torch.cat(out).to(points.dtype)


__all__ = ["GaussianScene", "read_ply", "write_ply", "ColorSpec", "RasterOption", "render_views", "render_rgb", "PARAM_NAMES", "DEFAULT_LRS", "inverse_sigmoid", "knn_mean_distance",
           "MAX_SH_DEGREE"]
