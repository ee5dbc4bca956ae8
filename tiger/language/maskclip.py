"""MaskCLIP dense CLIP features (SPEC §4, FeatUp's variant) and the CLIP text encoder.

The vision transformer runs as usual up to its last block; there self-attention is replaced by
its value path only, ``out_proj(v_proj(ln_1(x)))`` (no residual, no MLP), followed by
``post_layernorm`` and the visual projection: a ``projection_dim``-d (512 for ViT-B/16) feature
per 16x16 patch. Position embeddings are interpolated (bicubic) to any size divisible by 16.
"""
from __future__ import annotations

import inspect
import logging
from typing import Any, Sequence

import torch
import torch.nn.functional as F

from .templates import MASKCLIP_TEMPLATES

logger = logging.getLogger(__name__)

IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)
CLIP_MEAN = (0.48145466, 0.4578275, 0.40821073)
CLIP_STD = (0.26862954, 0.26130258, 0.27577711)
_NORMS = {"imagenet": (IMAGENET_MEAN, IMAGENET_STD), "clip": (CLIP_MEAN, CLIP_STD)}


def normalize_images(images: torch.Tensor, kind: str) -> torch.Tensor:
    """``(images - mean) / std`` for images [B, 3, H, W] in [0, 1]; kind 'imagenet' or 'clip'."""
    if kind not in _NORMS:
        raise ValueError(f"tiger.MaskCLIP: normalization must be one of {sorted(_NORMS)}, got {kind!r}")
    mean, std = (torch.tensor(v, device=images.device, dtype=images.dtype).view(1, 3, 1, 1) for v in _NORMS[kind])
    return (images - mean) / std


class MaskCLIP(torch.nn.Module):
    """Dense MaskCLIP features from a ``transformers.CLIPModel``.

    Args:
        clip_model: a ``CLIPModel`` (ViT vision tower).
        tokenizer: its tokenizer (needed only by :meth:`encode_text`).
        normalization: 'imagenet' (FeatUp's choice, default) or 'clip' (CLIP's own statistics).
    """

    def __init__(self, clip_model: Any, tokenizer: Any = None, normalization: str = "imagenet") -> None:
        super().__init__()
        if normalization not in _NORMS:
            raise ValueError(f"tiger.MaskCLIP: normalization must be one of {sorted(_NORMS)}, got {normalization!r}")
        self.clip = clip_model
        self.tokenizer = tokenizer
        self.normalization = normalization
        vm = clip_model.vision_model
        self.patch_size = int(vm.embeddings.patch_size)
        self.out_dim = int(clip_model.config.projection_dim)
        params = inspect.signature(vm.encoder.layers[0].forward).parameters
        self._legacy_layer_call = "causal_attention_mask" in params  # transformers < 5

    @classmethod
    def from_pretrained(cls, path=None, *, device="cpu", dtype=torch.float32, normalization="imagenet", **kwargs):
        """Load CLIP through :func:`tiger.models.load_clip` (same arguments) and wrap it."""
        from tiger.models.clip import load_clip

        bundle = load_clip(path, device=device, dtype=dtype, **kwargs)
        return cls(bundle.model, bundle.tokenizer, normalization)

    def vision_in(self, dtype: torch.dtype) -> "MaskCLIP":
        """This model's dense features with the vision tower's weights in ``dtype``: a copy of the
        vision tower and projection (no text encoder), cast once and kept while this model's
        weights stay the same (the implicit FeatUp fit runs ~2,000 backbone passes an image: in
        bf16 weights they take 0.56 s where bf16 autocast over float32 weights takes 0.67 s on
        the H100, per-view cosine 0.9999). Returns ``self`` when the weights already are ``dtype``."""
        if self.dtype == dtype:
            return self
        params = [*self.clip.vision_model.parameters(), *self.clip.visual_projection.parameters()]
        key = (dtype, tuple((p.data_ptr(), p._version) for p in params))
        cached = self.__dict__.get("_vision_copy")
        if cached is not None and cached[0] == key:
            return cached[1]
        tower = _VisionTower(self.clip, dtype)
        twin = MaskCLIP(tower, None, self.normalization)
        self.__dict__["_vision_copy"] = (key, twin)  # a plain attribute: not a submodule, not in state_dict
        return twin

    @property
    def device(self) -> torch.device:
        return self.clip.visual_projection.weight.device

    @property
    def dtype(self) -> torch.dtype:
        return self.clip.visual_projection.weight.dtype

    def position_embeddings(self, grid_h: int, grid_w: int) -> torch.Tensor:
        """Class + patch position embeddings [1 + grid_h * grid_w, D], patch part resampled bicubically
        with FeatUp's scale factors ((grid + 0.1) / side, ``recompute_scale_factor=False``)."""
        table = self.clip.vision_model.embeddings.position_embedding.weight
        n = table.shape[0] - 1
        side = int(round(n**0.5))
        if side * side != n:
            raise ValueError(f"tiger.MaskCLIP: the position table has {n} patch entries, not a square grid")
        cls_pos, patch_pos = table[:1], table[1:]
        if (grid_h, grid_w) != (side, side):
            grid = patch_pos.reshape(1, side, side, -1).permute(0, 3, 1, 2).float()
            # FeatUp's rule (featup/featurizers/maskclip/interpolate.py, from DINO): the scale
            # (g + 0.1) / side, not the target size, sets the sampling positions.
            grid = F.interpolate(grid, scale_factor=((grid_h + 0.1) / side, (grid_w + 0.1) / side),
                                 mode="bicubic", align_corners=False, recompute_scale_factor=False)
            if tuple(grid.shape[-2:]) != (grid_h, grid_w):  # floor(side * (g + 0.1) / side) == g
                raise RuntimeError(f"tiger.MaskCLIP: position grid {tuple(grid.shape[-2:])}, "
                                   f"expected {(grid_h, grid_w)}")
            patch_pos = grid.permute(0, 2, 3, 1).reshape(grid_h * grid_w, -1).to(table.dtype)
        return torch.cat([cls_pos, patch_pos], dim=0)

    def _run_layer(self, layer: Any, h: torch.Tensor) -> torch.Tensor:
        out = layer(h, None, None) if self._legacy_layer_call else layer(h, None)
        return out[0] if isinstance(out, tuple) else out

    @torch.no_grad()
    def forward(self, images: torch.Tensor, normalized: bool = False) -> torch.Tensor:
        """Dense features of images [B, 3, H, W] (RGB in [0, 1], H and W divisible by the patch size).

        Returns [B, projection_dim, H / 16, W / 16] (not L2-normalised) in float32.
        """
        if images.dim() != 4 or images.shape[1] != 3:
            raise ValueError(f"tiger.MaskCLIP: images must be [B, 3, H, W], got {tuple(images.shape)}")
        b, _, h, w = images.shape
        p = self.patch_size
        if h % p or w % p or h == 0 or w == 0:
            raise ValueError(f"tiger.MaskCLIP: image size {h}x{w} must be a positive multiple of the patch size {p}")
        vm = self.clip.vision_model
        x = images.to(device=self.device, dtype=self.dtype)
        if not normalized:
            x = normalize_images(x, self.normalization)
        patches = vm.embeddings.patch_embedding(x).flatten(2).transpose(1, 2)  # [B, N, D]
        cls_tok = vm.embeddings.class_embedding.to(patches.dtype).expand(b, 1, -1)
        tokens = torch.cat([cls_tok, patches], dim=1) + self.position_embeddings(h // p, w // p).unsqueeze(0)
        tokens = vm.pre_layrnorm(tokens)
        *layers, last = vm.encoder.layers
        for layer in layers:
            tokens = self._run_layer(layer, tokens)
        attn = last.self_attn
        v = attn.out_proj(attn.v_proj(last.layer_norm1(tokens)))
        feats = self.clip.visual_projection(vm.post_layernorm(v))[:, 1:]
        return feats.transpose(1, 2).reshape(b, -1, h // p, w // p).float()

    @torch.no_grad()
    def encode_text(
        self, texts: Sequence[str], templates: Sequence[str] | None = MASKCLIP_TEMPLATES, batch_size: int = 256
    ) -> torch.Tensor:
        """CLIP text embeddings [Q, projection_dim], L2-normalised, float32.

        Each query is written into every template (``'{}'`` replaced by the text), the normalised
        embeddings are averaged over templates and normalised again (MaskCLIP's prompt ensembling).
        ``templates=None`` (or empty) embeds the raw texts.
        """
        if isinstance(texts, str):
            texts = [texts]
        if len(texts) == 0:
            return torch.empty(0, self.out_dim, device=self.device)
        if self.tokenizer is None:
            raise ValueError("tiger.MaskCLIP.encode_text needs the CLIP tokenizer (load with MaskCLIP.from_pretrained)")
        temps = list(templates) if templates else ["{}"]
        prompts = [t.format(q) for q in texts for t in temps]
        embs = []
        max_len = int(getattr(self.clip.config.text_config, "max_position_embeddings", 77))
        for i in range(0, len(prompts), batch_size):
            tok = self.tokenizer(prompts[i : i + batch_size], padding=True, truncation=True, max_length=max_len,
                                 return_tensors="pt")
            tok = {k: v.to(self.device) for k, v in tok.items() if k in ("input_ids", "attention_mask")}
            out = self.clip.get_text_features(**tok)
            out = out if isinstance(out, torch.Tensor) else out.pooler_output
            embs.append(F.normalize(out.float(), dim=-1))
        emb = torch.cat(embs).reshape(len(texts), len(temps), -1).mean(1)
        return F.normalize(emb, dim=-1)


class _VisionTower(torch.nn.Module):
    """The parts of a ``CLIPModel`` that :meth:`MaskCLIP.forward` reads, copied in another dtype."""

    def __init__(self, clip_model: Any, dtype: torch.dtype) -> None:
        import copy

        super().__init__()
        self.config = clip_model.config
        self.vision_model = copy.deepcopy(clip_model.vision_model).to(dtype)
        self.visual_projection = copy.deepcopy(clip_model.visual_projection).to(dtype)


def resize_for_patches(images: torch.Tensor, long_side: int, patch: int = 16) -> torch.Tensor:
    """Resize images [B, 3, H, W] so the long side is ``long_side`` and both sides are multiples of
    ``patch`` (aspect ratio kept as nearly as the rounding allows); bilinear with antialiasing."""
    h, w = images.shape[-2:]
    scale = long_side / max(h, w)
    nh = max(patch, int(round(h * scale / patch)) * patch)
    nw = max(patch, int(round(w * scale / patch)) * patch)
    return F.interpolate(images, size=(nh, nw), mode="bilinear", align_corners=False, antialias=True)
