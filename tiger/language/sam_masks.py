"""SAM finest-level automatic masks (SPEC §4; SAM's automatic mask generator as LangSplat uses it).

A 32x32 grid of single-point prompts; of SAM's three multimask outputs the finest (index 0) is
kept; masks are filtered by predicted IoU (> 0.7) and stability (>= 0.85), deduplicated by box
NMS (IoU 0.7, ``tiger::box_nms``), cleaned of small holes and islands (< 100 px) with a second
box NMS preferring unchanged masks, masks under 100 px are dropped, and LangSplat's mask NMS
(IoU 0.8, score = IoU x stability > 0.7, nested 0.5; ``tiger::mask_nms``) runs last. Masks are
produced directly at the requested working resolution.

Every stage runs on the model's device with a handful of host synchronisations per image (none
per mask): the prompts are decoded in large batches, the clean-up is ``tiger::remove_small_regions``
(connected components by union-find, CPU and CUDA kernels) and the id map is one max-reduction.
"""
from __future__ import annotations

import dataclasses
import logging
import os
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F

from tiger.ops.components import remove_small_regions as clean_small_regions
from tiger.ops.nms import box_nms, mask_nms
from tiger.utils.threads import thread_map

from .sam_decoder import SamGridDecoder

logger = logging.getLogger(__name__)

SAM_PRECISIONS = ("auto", "bf16", "fp32")
SAM_MEAN = (0.485, 0.456, 0.406)  # SAM's pixel_mean / 255
SAM_STD = (0.229, 0.224, 0.225)


@dataclass
class SamMaskConfig:
    """Thresholds of SAM's automatic mask generator as set by SPEC §4 and LangSplat.

    ``points_per_batch`` prompts go through SAM's decoder at once (None: as many as fit 40 % of
    the CUDA device's memory, or 2 GiB on the CPU, at most the whole grid; only memory and speed
    depend on it, the masks up to float rounding).

    ``precision``: 'bf16' runs the image encoder with bfloat16 weights and the prompt decoder under
    bfloat16 autocast (as SAM 2's own predictor runs; LayerNorm, softmax and the mask logits stay
    float32): on an H100 a 1080p image with ~300 masks takes 0.29 s against 0.50 s in float32.
    The masks are not bit-identical to float32's (on random full-size weights they differ
    visibly, see benchmarks/masks.py ``--agreement``). 'fp32' runs everything in float32; 'auto'
    (the default) is 'bf16' on CUDA and 'fp32' elsewhere. ``decoder_bf16`` turns on the decoder's
    autocast alone on a float32 SAM."""

    points_per_side: int = 32
    points_per_batch: int | None = None
    precision: str = "auto"
    decoder_bf16: bool = False
    level: int = 0
    pred_iou_thresh: float = 0.7
    stability_score_thresh: float = 0.85
    stability_score_offset: float = 1.0
    mask_threshold: float = 0.0
    box_nms_thresh: float = 0.7
    min_mask_region_area: int = 100
    mask_nms_iou: float = 0.8
    mask_nms_score: float = 0.7
    mask_nms_inner: float = 0.5

    def resolved(self, device: torch.device | str) -> "SamMaskConfig":
        """This config with ``precision`` 'auto' made concrete for ``device`` ('bf16' on CUDA)."""
        if self.precision not in SAM_PRECISIONS:
            raise ValueError(f"tiger.SamMaskConfig: precision must be one of {SAM_PRECISIONS}, got {self.precision!r}")
        if self.precision != "auto":
            return self
        bf16 = torch.device(device).type == "cuda"
        return dataclasses.replace(self, precision="bf16" if bf16 else "fp32")


@dataclass
class SamMasks:
    """Masks [M, H, W] bool with predicted IoU [M] and stability [M], ordered by decreasing
    IoU x stability."""

    masks: torch.Tensor
    iou: torch.Tensor
    stability: torch.Tensor

    def id_map(self) -> torch.Tensor:
        """Per-pixel mask id [H, W] int64 (-1: in no mask). Where masks overlap the smallest wins,
        so the finest segment decides (masks painted from the largest down; between equal areas the
        higher index wins). One max-reduction over the masks, no host synchronisation."""
        m, h, w = self.masks.shape
        dev = self.masks.device
        if m == 0:
            return torch.full((h, w), -1, dtype=torch.int64, device=dev)
        order = torch.argsort(self.masks.flatten(1).sum(1), descending=True, stable=True)  # paint order
        rank_dtype = torch.int16 if m < 2**15 else torch.int32
        rank = torch.empty(m, dtype=rank_dtype, device=dev)
        rank[order] = torch.arange(1, m + 1, dtype=rank_dtype, device=dev)  # painted later: higher rank
        top = torch.zeros(h, w, dtype=rank_dtype, device=dev)
        for s in range(0, m, 32):  # bounds the [chunk, H, W] temporary
            chunk = torch.where(self.masks[s : s + 32], rank[s : s + 32].view(-1, 1, 1), 0).amax(0)
            top = torch.maximum(top, chunk)
        top = top.long()
        return torch.where(top > 0, order[(top - 1).clamp_min(0)], -1)


def point_grid(n: int) -> torch.Tensor:
    """SAM's ``build_point_grid``: [n*n, 2] (x, y) in [0, 1], cell centres, x fastest."""
    side = (torch.arange(n, dtype=torch.float64) + 0.5) / n
    y, x = torch.meshgrid(side, side, indexing="ij")
    return torch.stack([x.reshape(-1), y.reshape(-1)], dim=1)


def stability_score(logits: torch.Tensor, threshold: float, offset: float) -> torch.Tensor:
    """SAM's stability: IoU of the masks thresholded at threshold +/- offset, for logits [B, H, W]."""
    inter = (logits > threshold + offset).flatten(1).sum(1)
    union = (logits > threshold - offset).flatten(1).sum(1)
    return inter.float() / union.float().clamp_min(1)


def masks_to_boxes(masks: torch.Tensor) -> torch.Tensor:
    """Tight boxes [M, 4] (x0, y0, x1, y1; inclusive pixel indices, SAM's convention; 0 for empty)."""
    m, h, w = masks.shape
    if m == 0:
        return torch.zeros(0, 4, device=masks.device)
    rows, cols = masks.any(2), masks.any(1)
    ar_h = torch.arange(h, device=masks.device)
    ar_w = torch.arange(w, device=masks.device)
    y1 = torch.where(rows, ar_h, -1).amax(1)
    y0 = torch.where(rows, ar_h, h).amin(1)
    x1 = torch.where(cols, ar_w, -1).amax(1)
    x0 = torch.where(cols, ar_w, w).amin(1)
    boxes = torch.stack([x0, y0, x1, y1], 1).float()
    return torch.where((y1 >= 0).unsqueeze(1), boxes, torch.zeros_like(boxes))


def _label(binary: np.ndarray) -> tuple[np.ndarray, int]:
    try:  # OpenCV's labelling is the fastest when installed; scipy is the always-present fallback
        import cv2  # type: ignore

        n, labels = cv2.connectedComponents(binary.astype(np.uint8), connectivity=8)
        return labels, n - 1
    except ImportError:
        from scipy import ndimage

        labels, n = ndimage.label(binary, structure=np.ones((3, 3), dtype=bool))
        return labels, n


def remove_small_regions_of_mask(mask: np.ndarray, area_thresh: int, mode: str) -> tuple[np.ndarray, bool]:
    """SAM's ``remove_small_regions`` on one mask [H, W] as SAM writes it: fill holes (mode 'holes')
    or drop islands ('islands') smaller than ``area_thresh`` pixels (8-connectivity); an all-small
    mask keeps its largest island. ``tiger::remove_small_regions`` gives the same result for all
    masks at once on the GPU."""
    if mode not in ("holes", "islands"):
        raise ValueError(f"tiger.remove_small_regions: mode must be 'holes' or 'islands', got {mode!r}")
    holes = mode == "holes"
    labels, n = _label(holes ^ mask)
    sizes = np.bincount(labels.ravel(), minlength=n + 1)[1:]
    small = np.nonzero(sizes < area_thresh)[0] + 1
    if small.size == 0:
        return mask, False
    keep = np.zeros(n + 1, dtype=bool)  # lookup table: label -> in the result
    if holes:
        keep[0] = True
        keep[small] = True
    else:
        keep[1:] = True
        keep[small] = False
        if not keep.any():
            keep[int(np.argmax(sizes)) + 1] = True
    return keep[labels], True


def clean_masks_on_host(masks: torch.Tensor, area_thresh: int) -> tuple[torch.Tensor, torch.Tensor]:
    """SAM's clean-up of masks [M, H, W] bool (holes, then islands, by :func:`remove_small_regions_of_mask`)
    on host copies, one mask per thread (OpenCV releases the GIL): (masks, changed [M] bool)."""
    host = masks.cpu().numpy().copy()
    changed = np.zeros(len(host), dtype=bool)

    def one(k: int) -> None:
        m, c1 = remove_small_regions_of_mask(host[k], area_thresh, "holes")
        m, c2 = remove_small_regions_of_mask(m, area_thresh, "islands")
        if c1 or c2:
            host[k], changed[k] = m, True

    thread_map(one, range(len(host)), min(16, os.cpu_count() or 1), "tiger-sam-cleanup")
    return torch.from_numpy(host).to(masks.device), torch.from_numpy(changed).to(masks.device)


class SamMaskGenerator:
    """Automatic finest-level masks from a ``transformers.SamModel``.

    ``generator(image [3, H, W] in [0, 1], size=(h, w)) -> SamMasks`` at the working size ``size``
    (default the image size). The config's ``precision`` is resolved for the model's device; with
    'bf16' the model's image encoder is converted to bfloat16 in place (the generator owns the model).
    """

    def __init__(self, model: Any, config: SamMaskConfig | None = None, decoder: Any = None) -> None:
        self.model = model
        self.config = (config or SamMaskConfig()).resolved(next(model.parameters()).device)
        bf16 = self.config.precision == "bf16"
        if bf16 and self.encoder_dtype == torch.float32:
            model.vision_encoder.to(torch.bfloat16)
        self.input_size = int(model.config.vision_config.image_size)
        # the prompt decoder: ``prepare(embedding) -> tokens`` and ``(tokens, points [P, 2]) ->
        # (low-res logits [P, h, w], predicted IoU [P])``; SAM's own layers by default
        self.decoder = decoder if decoder is not None else SamGridDecoder(
            model, level=self.config.level, autocast=self.config.decoder_bf16 or bf16)

    @classmethod
    def from_pretrained(cls, path=None, *, device="cpu", dtype=torch.float32,
                        mask_config: SamMaskConfig | None = None, **kwargs) -> "SamMaskGenerator":
        """Load SAM through :func:`tiger.models.load_sam` (``path``, ``config``, ... as there); the
        mask config's ``precision`` then decides the image encoder's dtype (see :class:`SamMaskConfig`)."""
        from tiger.models.sam import load_sam

        return cls(load_sam(path, device=device, dtype=dtype, **kwargs), mask_config)

    @property
    def device(self) -> torch.device:
        return next(self.model.parameters()).device

    @property
    def dtype(self) -> torch.dtype:
        """The prompt decoder's weight dtype (the image embedding is handed over in it)."""
        return self._weight_dtype("mask_decoder")

    @property
    def encoder_dtype(self) -> torch.dtype:
        """The image encoder's weight dtype (bfloat16 with ``precision='bf16'``)."""
        return self._weight_dtype("vision_encoder")

    def _weight_dtype(self, part: str) -> torch.dtype:
        """The dtype of the model's ``part`` (the whole model's first weight for a model without it)."""
        module = getattr(self.model, part, None)
        weights = module.parameters() if isinstance(module, torch.nn.Module) else self.model.parameters()
        return next(weights).dtype

    def preprocess(self, image: torch.Tensor) -> tuple[torch.Tensor, tuple[int, int]]:
        """SAM input [1, 3, S, S]: long side resized to S, normalised, zero-padded bottom/right."""
        if image.dim() != 3 or image.shape[0] != 3:
            raise ValueError(f"tiger.SamMaskGenerator: image must be [3, H, W], got {tuple(image.shape)}")
        h, w = image.shape[-2:]
        s = self.input_size
        scale = s / max(h, w)
        rh, rw = int(h * scale + 0.5), int(w * scale + 0.5)
        x = F.interpolate(image[None].float(), size=(rh, rw), mode="bilinear", align_corners=False, antialias=True)
        mean = torch.tensor(SAM_MEAN, device=x.device).view(1, 3, 1, 1)
        std = torch.tensor(SAM_STD, device=x.device).view(1, 3, 1, 1)
        x = F.pad((x - mean) / std, (0, s - rw, 0, s - rh))
        return x, (rh, rw)

    def _upscale(self, low: torch.Tensor, resized: tuple[int, int], size: tuple[int, int]) -> torch.Tensor:
        """SAM's postprocess_masks: low-res logits [B, h, w] -> input frame -> crop -> ``size``.

        Only the low-res rows and columns the crop reads are upsampled (the input frame's padding is
        never computed): with the same scale factor, output pixel i reads source (i + 0.5) / f - 0.5
        either way, so the result is bit-identical to upsampling the whole frame and cropping."""
        s, lh, lw = self.input_size, low.shape[-2], low.shape[-1]
        fh, fw = s // lh, s // lw
        if fh * lh != s or fw * lw != s:  # not an integer factor: upsample the whole frame
            x = F.interpolate(low[:, None].float(), size=(s, s), mode="bilinear", align_corners=False)
        else:
            kh, kw = min(lh, -(-resized[0] // fh) + 1), min(lw, -(-resized[1] // fw) + 1)
            x = F.interpolate(low[:, None, :kh, :kw].float(), scale_factor=(fh, fw), mode="bilinear",
                              align_corners=False, recompute_scale_factor=False)
        x = x[..., : resized[0], : resized[1]]
        return F.interpolate(x, size=size, mode="bilinear", align_corners=False)[:, 0]

    def _batch(self) -> int:
        """Prompts per decoder call (see :class:`SamMaskConfig`)."""
        if self.config.points_per_batch is not None:
            return max(1, int(self.config.points_per_batch))
        grid = self.config.points_per_side ** 2
        # the peak per prompt, in the upscaling: two [16 L, C / 8] float32 maps (a product and its
        # GELU) beside two [L, C] ones (L image tokens)
        dec = self.model.config.mask_decoder_config
        tokens = self.model.config.prompt_encoder_config.image_embedding_size ** 2
        per_prompt = 2 * 16 * tokens * (dec.hidden_size // 8) * 4 + 2 * tokens * dec.hidden_size * 4
        if self.device.type == "cuda":
            budget = int(0.4 * torch.cuda.get_device_properties(self.device).total_memory)
        else:
            budget = 2 << 30
        fit = budget // per_prompt
        return max(1, min(grid, fit // 64 * 64 or fit))

    @torch.no_grad()
    def embed(self, image: torch.Tensor) -> tuple[torch.Tensor, tuple[int, int]]:
        """SAM's image embedding [1, C, h, w] (float32 unless the whole model is in another dtype) of
        image [3, H, W] and the resized (h, w) inside SAM's input frame."""
        pixels, resized = self.preprocess(image.to(self.device))
        emb = self.model.get_image_embeddings(pixels.to(self.encoder_dtype))
        return emb.to(self.dtype), resized

    @torch.no_grad()
    def decode(self, emb: torch.Tensor, resized: tuple[int, int]) -> tuple[torch.Tensor, torch.Tensor]:
        """The point grid through SAM's decoder (:class:`SamGridDecoder`: the image side prepared
        once), ``points_per_batch`` prompts at a time, no host synchronisation: the chosen level's
        low-resolution logits [P, 256, 256] float32 and predicted IoU [P], in prompt order."""
        cfg = self.config
        pts = point_grid(cfg.points_per_side) * torch.tensor([resized[1], resized[0]], dtype=torch.float64)
        pts = pts.to(self.device, torch.float32)
        tokens = self.decoder.prepare(emb)
        batch = self._batch()
        if batch >= pts.shape[0]:
            return self.decoder(tokens, pts)
        lows, ious = [], []
        for i in range(0, pts.shape[0], batch):
            low, iou = self.decoder(tokens, pts[i : i + batch])
            lows.append(low)
            ious.append(iou)
        return torch.cat(lows), torch.cat(ious)

    @torch.no_grad()
    def select(self, low: torch.Tensor, iou: torch.Tensor, resized: tuple[int, int], size: tuple[int, int]):
        """SAM's filters on decoded prompts: IoU > pred_iou_thresh (one host read for all prompts),
        then the kept logits upscaled to ``size`` (in chunks bounded by memory, which do not change
        the masks), stability >= stability_score_thresh. Returns (masks [N, h, w] bool, iou [N],
        stability [N])."""
        cfg = self.config
        keep = torch.nonzero(iou > cfg.pred_iou_thresh).squeeze(1)
        low, iou = low.index_select(0, keep), iou.index_select(0, keep)
        n = keep.shape[0]
        masks = torch.empty(n, *size, dtype=torch.bool, device=self.device)
        stab = torch.empty(n, device=self.device)
        s = self.input_size
        chunk = max(1, (1 << 27) // (s * s + size[0] * size[1]))  # float32 upscale temporaries <= 1 GiB
        for i in range(0, n, chunk):
            logits = self._upscale(low[i : i + chunk], resized, size)
            stab[i : i + chunk] = stability_score(logits, cfg.mask_threshold, cfg.stability_score_offset)
            masks[i : i + chunk] = logits > cfg.mask_threshold
        ok = torch.nonzero(stab >= cfg.stability_score_thresh).squeeze(1)
        if ok.shape[0] == n:
            return masks, iou, stab
        return masks.index_select(0, ok), iou.index_select(0, ok), stab.index_select(0, ok)

    @torch.no_grad()
    def predict(self, image: torch.Tensor, size: tuple[int, int] | None = None):
        """Raw point-grid predictions passing the IoU/stability filters: (masks [N, h, w] bool,
        iou [N], stability [N]), before any NMS, in prompt order (:meth:`embed`, :meth:`decode`,
        :meth:`select`)."""
        size = tuple(size) if size is not None else tuple(image.shape[-2:])
        emb, resized = self.embed(image)
        low, iou = self.decode(emb, resized)
        return self.select(low, iou, resized, size)

    @torch.no_grad()
    def __call__(self, image: torch.Tensor, size: tuple[int, int] | None = None) -> SamMasks:
        """Finest-level automatic masks of image [3, H, W] (RGB in [0, 1]) at ``size`` (h, w)."""
        return self.postprocess(*self.predict(image, size))

    @torch.no_grad()
    def postprocess(self, masks: torch.Tensor, iou: torch.Tensor, stab: torch.Tensor) -> SamMasks:
        """Box NMS, small-region clean-up, second box NMS, area filter and mask NMS of the filtered
        predictions (masks [N, h, w] bool, iou [N], stability [N]), on their device."""
        cfg = self.config
        keep = box_nms(masks_to_boxes(masks), iou, cfg.box_nms_thresh)
        masks, iou, stab = masks[keep], iou[keep], stab[keep]
        if cfg.min_mask_region_area > 0 and masks.shape[0] > 0:
            masks, changed = self._clean(masks)
            keep = box_nms(masks_to_boxes(masks), (~changed).float(), cfg.box_nms_thresh)
            masks, iou, stab = masks[keep], iou[keep], stab[keep]
            big = torch.nonzero(masks.flatten(1).sum(1) >= cfg.min_mask_region_area).squeeze(1)
            masks, iou, stab = masks[big], iou[big], stab[big]
        keep = mask_nms(masks, iou * stab, cfg.mask_nms_iou, cfg.mask_nms_score, cfg.mask_nms_inner)
        return SamMasks(masks[keep], iou[keep], stab[keep])

    def _clean(self, masks: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Small holes, then small islands, removed from every mask [M, H, W] bool; returns (masks,
        changed [M] bool). On the GPU all masks at once (``tiger::remove_small_regions``); on the CPU
        OpenCV's labelling per mask is the faster of the two exact paths."""
        if masks.device.type == "cpu":
            return clean_masks_on_host(masks, self.config.min_mask_region_area)
        return clean_small_regions(masks, self.config.min_mask_region_area)
