"""Edit quality metrics (SPEC §6): CLIP direction similarity, CLIP direction consistency, locality.

* **CLIP text-image direction similarity** (Instruct-NeRF2NeRF §5, after StyleGAN-NADA): for each
  view, the cosine between the change of the image embedding and the change of the caption
  embedding, ``cos(E_I(after) - E_I(before), E_T(caption_after) - E_T(caption_before))``; the
  embeddings are L2-normalised before the differences are taken. Reported per view and as the mean.
* **CLIP direction consistency** (Instruct-NeRF2NeRF §5): along a camera path, for each pair of
  neighbouring views i, i+1, the cosine between the embedding change of the edited renders and
  that of the original renders, ``cos(E_I(after_{i+1}) - E_I(after_i), E_I(before_{i+1}) -
  E_I(before_i))``: an edit that flickers between views changes the path's direction.
* **Locality**: PSNR between the renders before and after the edit over the pixels *outside* the
  edited object's footprint, dilated by ``dilate_px`` pixels. The footprint is where the object's
  Gaussians (before, and after: children included) cover at least ``coverage`` of a pixel. An edit
  that leaks into the rest of the scene lowers it; a perfectly local edit gives MSE 0, reported as
  :data:`PSNR_CAP` dB (JSON has no infinity). The object's own faint edge counts as outside too:
  pixels it covers by less than ``coverage`` further than ``dilate_px`` from its footprint change
  with any recolouring, so even the exact recolour of an object scores below the cap (demo ball at
  density 0.25: 75 dB from 128² views). :func:`locality` therefore splits its error by where it
  comes from (``parts``): the object's faint edge (``fringe``), pixels only the edited Gaussians
  reach (``spread``), and pixels no edited Gaussian reaches before or after (``rest``: these
  change only if Gaussians outside the object did).
"""
from __future__ import annotations

import logging
import math
from typing import TYPE_CHECKING, Optional, Sequence, Union

import torch
import torch.nn.functional as F

from tiger.render import Camera
from tiger.scene import GaussianScene, render_rgb
from tiger.utils.filters import dilate

if TYPE_CHECKING:
    from transformers import CLIPModel

    from tiger.language.maskclip import MaskCLIP

log = logging.getLogger(__name__)

PSNR_CAP = 100.0


def _check_pairs(before: torch.Tensor, after: torch.Tensor, what: str) -> None:
    if before.shape != after.shape or before.dim() != 2:
        raise ValueError(f"tiger.eval.edit: {what} before/after must both be [V, F], got "
                         f"{list(before.shape)} and {list(after.shape)}")


def clip_direction_similarity(image_before: torch.Tensor, image_after: torch.Tensor,
                              text_before: torch.Tensor, text_after: torch.Tensor) -> torch.Tensor:
    """[V] cosine between each view's image-embedding change and the caption-embedding change.

    Args:
        image_before, image_after: [V, F] CLIP image embeddings of the same views before / after.
        text_before, text_after: [F] CLIP text embeddings of the captions before / after.
    """
    _check_pairs(image_before, image_after, "image embeddings")
    if text_before.shape != (image_before.shape[1],) or text_after.shape != text_before.shape:
        raise ValueError(f"tiger.eval.edit: text embeddings must be [F={image_before.shape[1]}], got "
                         f"{list(text_before.shape)} and {list(text_after.shape)}")
    di = F.normalize(image_after.double(), dim=-1) - F.normalize(image_before.double(), dim=-1)
    dt = F.normalize(text_after.double(), dim=-1) - F.normalize(text_before.double(), dim=-1)
    return F.cosine_similarity(di, dt.expand_as(di), dim=-1, eps=1e-12)


def clip_direction_consistency(image_before: torch.Tensor, image_after: torch.Tensor) -> torch.Tensor:
    """[V-1] cosine between the edited and the original embedding change from view i to view i+1.

    Args:
        image_before, image_after: [V, F] CLIP image embeddings of V views along a path (V >= 2).
    """
    _check_pairs(image_before, image_after, "image embeddings")
    if image_before.shape[0] < 2:
        raise ValueError("tiger.eval.edit: direction consistency needs at least 2 views along a path")
    b = F.normalize(image_before.double(), dim=-1)
    a = F.normalize(image_after.double(), dim=-1)
    return F.cosine_similarity(a[1:] - a[:-1], b[1:] - b[:-1], dim=-1, eps=1e-12)


def dilate_mask(mask: torch.Tensor, px: int) -> torch.Tensor:
    """[V, H, W] bool mask grown by ``px`` pixels (a (2 px + 1)² square max filter)."""
    if mask.dim() != 3:
        raise ValueError(f"tiger.eval.edit: masks must be [V, H, W], got {list(mask.shape)}")
    return dilate(mask, max(int(px), 0), "square")


def psnr_outside(before: torch.Tensor, after: torch.Tensor, masks: torch.Tensor, dilate_px: int = 4) -> dict:
    """PSNR (dB, peak 1) of ``after`` vs ``before`` over the pixels outside the dilated ``masks``.

    Args:
        before, after: [V, H, W, C] images in [0, 1].
        masks: [V, H, W] bool, the edited object's footprint per view.
        dilate_px: dilation of the footprint before it is excluded.
    Returns:
        {"psnr": dB (capped at PSNR_CAP), "mse": mean squared error, "pixels": pixels compared,
        "fraction": their share of all pixels}.
    """
    if before.shape != after.shape or before.dim() != 4:
        raise ValueError(f"tiger.eval.edit: before/after renders must both be [V, H, W, C], got "
                         f"{list(before.shape)} and {list(after.shape)}")
    if masks.shape != before.shape[:3]:
        raise ValueError(f"tiger.eval.edit: masks must be [V, H, W] = {list(before.shape[:3])}, got {list(masks.shape)}")
    outside = ~dilate_mask(masks.to(before.device), dilate_px)
    if not bool(outside.any()):
        raise ValueError("tiger.eval.edit: the dilated object mask covers every pixel; nothing to compare")
    return _psnr_over(before, after, outside)


def _psnr_over(before: torch.Tensor, after: torch.Tensor, outside: torch.Tensor) -> dict:
    """:func:`psnr_outside`'s result over the (non-empty) ``outside`` pixels [V, H, W]."""
    n = int(outside.sum())
    err = (after.double() - before.double()).square().mean(-1)
    mse = float(err[outside].mean())
    return {"psnr": _psnr(mse), "mse": mse, "pixels": n, "fraction": n / outside.numel()}


def _psnr(mse: float) -> float:
    """dB at peak 1, capped at :data:`PSNR_CAP`."""
    return PSNR_CAP if mse <= 10 ** (-PSNR_CAP / 10) else -10 * math.log10(mse)


def locality_parts(before: torch.Tensor, after: torch.Tensor, outside: torch.Tensor, reach_before: torch.Tensor,
                   reach_after: torch.Tensor) -> dict:
    """Where the error of :func:`psnr_outside` comes from: its ``outside`` pixels split into
    ``fringe`` (the edited Gaussians reached them before the edit: the object's faint edge),
    ``spread`` (reached only after the edit) and ``rest`` (reached by no edited Gaussian, before or
    after: they can differ only if other Gaussians changed, or by float rounding).
    :func:`locality` takes "reached" as :func:`edited_reach`: an edited Gaussian at or above the
    alpha threshold anywhere in the pixel's list, composited or not.

    Args:
        before, after: [V, H, W, C] images in [0, 1].
        outside: [V, H, W] bool, the pixels the locality PSNR compares.
        reach_before, reach_after: [V, H, W] bool, where the edited Gaussians contribute at all.
    Returns:
        per part {"psnr": dB of the part's share of the MSE (its squared errors over all
        ``outside`` pixels: the three shares add up to the MSE), "pixels", "max_abs_err"}.
    """
    err = (after.double() - before.double()).square().mean(-1)
    diff = (after.double() - before.double()).abs().amax(-1)
    n = max(int(outside.sum()), 1)
    parts = {"fringe": outside & reach_before, "spread": outside & reach_after & ~reach_before,
             "rest": outside & ~reach_before & ~reach_after}
    return {name: {"psnr": _psnr(float(err[sel].sum()) / n), "pixels": int(sel.sum()),
                   "max_abs_err": float(diff[sel].max()) if bool(sel.any()) else 0.0}
            for name, sel in parts.items()}


def locality(before: GaussianScene, after: GaussianScene, cameras: Sequence[Camera], edited_before: torch.Tensor,
             edited_after: torch.Tensor, dilate_px: int = 4, coverage: float = 0.02,
             background: Optional[torch.Tensor] = None) -> dict:
    """Locality PSNR of an edit over ``cameras``: renders of ``before`` and ``after`` (scenes)
    compared outside the union of the edited Gaussians' footprints (``edited_before`` [N_before]
    and ``edited_after`` [N_after] bool), dilated by ``dilate_px``. See :func:`psnr_outside`; the
    result's ``parts`` splits the error by :func:`locality_parts`. When the dilated footprints
    cover every pixel of every view nothing is compared: ``psnr``, ``mse`` and ``parts`` are None
    (a warning is logged) instead of an error after the edit has run."""
    for name, scene, sel in (("edited_before", before, edited_before), ("edited_after", after, edited_after)):
        if sel.shape != (len(scene),) or sel.dtype != torch.bool:
            raise ValueError(f"tiger.eval.edit: {name} must be [N={len(scene)}] bool, got {list(sel.shape)} {sel.dtype}")
    rb, fb = render_rgb(before, cameras, background, footprint=edited_before)
    ra, fa = render_rgb(after, cameras, background, footprint=edited_after)
    masks = (fb > coverage) | (fa > coverage)
    outside = ~dilate_mask(masks.to(rb.device), dilate_px)
    if not bool(outside.any()):  # an object that fills every view: locality is not measurable here
        log.warning("locality: the edited Gaussians' dilated footprint covers every pixel of the %d views; "
                    "nothing to compare", len(cameras))
        return {"psnr": None, "mse": None, "pixels": 0, "fraction": 0.0, "dilate_px": int(dilate_px), "parts": None}
    out = _psnr_over(rb, ra, outside)
    out["dilate_px"] = int(dilate_px)
    out["parts"] = locality_parts(rb, ra, outside, edited_reach(before, cameras, edited_before),
                                  edited_reach(after, cameras, edited_after))
    return out


def locality_text(loc: dict, where: str = "the object") -> str:
    """One line for a summary: the locality PSNR of :func:`locality`'s result, or why there is none."""
    if loc["psnr"] is None:
        return "locality: not measured (the edited footprint covers every pixel of the views)"
    return f"locality PSNR outside {where}: {loc['psnr']:.2f} dB ({_percent(loc['fraction'])} of the pixels)"


def _percent(share: float) -> str:
    """A share as a percentage that never rounds a nonzero share to 0 % (or a partial one to 100 %)."""
    pct = 100.0 * float(share)
    if 0.0 < pct < 0.05:
        return "<0.1%"
    if 99.95 < pct < 100.0:
        return ">99.9%"
    return f"{pct:.1f}%" if pct < 10.0 or pct > 90.0 else f"{pct:.0f}%"


def edited_reach(scene: GaussianScene, cameras: Sequence[Camera], edited: torch.Tensor) -> torch.Tensor:
    """[V, H, W] bool: the pixels where some ``edited`` Gaussian ([N] bool) reaches the alpha
    threshold, wherever it lies in the pixel's depth order.

    Not the composited footprint (``render_rgb(footprint=)`` > 0): a Gaussian that would take the
    pixel's transmittance below ``t_min`` ends the walk without being composited, so an edited
    Gaussian can decide where a pixel stops (and which Gaussians behind it are drawn) with a
    footprint of exactly 0. Rendered alone, the edited Gaussians' first one at or above the
    threshold is always composited (nothing in front of it), so their footprint is > 0 exactly
    where one reaches the pixel.
    """
    if not bool(edited.any()):
        return torch.zeros(len(cameras), cameras[0].height, cameras[0].width, dtype=torch.bool, device=scene.device)
    alone = scene.subset(edited)
    _, foot = render_rgb(alone, cameras, footprint=torch.ones(len(alone), dtype=torch.bool, device=scene.device))
    return foot > 0


@torch.no_grad()
def clip_image_embeddings(clip: Union["MaskCLIP", "CLIPModel"], images: torch.Tensor, size: int = 224) -> torch.Tensor:
    """[V, F] L2-normalised CLIP image embeddings of ``images`` [V, 3, H, W] in [0, 1].

    ``clip`` is a :class:`tiger.language.maskclip.MaskCLIP` (its ``clip`` CLIPModel is used, with
    CLIP's own normalisation) or a ``transformers.CLIPModel``. Images are resized (bilinear,
    antialiased) to ``size`` x ``size``, CLIP's input (its ``image_size`` when it has one).
    """
    from tiger.language.maskclip import normalize_images

    model = getattr(clip, "clip", clip)
    if images.dim() != 4 or images.shape[1] != 3:
        raise ValueError(f"tiger.eval.edit: images must be [V, 3, H, W], got {list(images.shape)}")
    size = int(getattr(getattr(model.config, "vision_config", None), "image_size", size) or size)
    w = model.visual_projection.weight
    x = F.interpolate(images.to(w.device, torch.float32), size=(size, size), mode="bilinear",
                      align_corners=False, antialias=True)
    out = model.get_image_features(pixel_values=normalize_images(x, "clip").to(w.dtype))
    out = out if isinstance(out, torch.Tensor) else out.pooler_output
    return F.normalize(out.float(), dim=-1)


def clip_metrics(clip: Union["MaskCLIP", "CLIPModel"], before: torch.Tensor, after: torch.Tensor, caption_before: str,
                 caption_after: str) -> dict:
    """CLIP direction similarity and consistency for renders ``before``/``after`` [V, 3, H, W]
    along a path, with captions embedded by ``clip.encode_text`` (no templates)."""
    eb, ea = clip_image_embeddings(clip, before), clip_image_embeddings(clip, after)
    t = clip.encode_text([caption_before, caption_after], templates=None).float().to(eb.device)
    sim = clip_direction_similarity(eb, ea, t[0], t[1])
    out = {"clip_direction_similarity": float(sim.mean()), "clip_direction_similarity_per_view": sim.tolist()}
    if before.shape[0] >= 2:
        cons = clip_direction_consistency(eb, ea)
        out.update(clip_direction_consistency=float(cons.mean()), clip_direction_consistency_per_pair=cons.tolist())
    return out


__all__ = ["PSNR_CAP", "clip_direction_consistency", "clip_direction_similarity", "clip_image_embeddings",
           "clip_metrics", "dilate_mask", "edited_reach", "locality", "locality_parts", "locality_text", "psnr_outside"]
