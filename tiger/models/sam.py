"""SAM (``facebook/sam-vit-huge``) from a Hugging Face folder or the original ``sam_vit_h_4b8939.pth``.

The original checkpoint's keys are renamed to ``transformers.SamModel``'s, and the
architecture (width, depth, global-attention blocks, window size) is read off the tensors.
"""
from __future__ import annotations

import logging
import re
from pathlib import Path
from typing import Any, Mapping

import torch

from tiger.utils.lazy import require

from .paths import ConfigLike, PathLike, resolve_model_path

logger = logging.getLogger(__name__)

# Original (segment-anything) key fragments -> transformers.SamModel key fragments, in order.
_RENAMES: tuple[tuple[str, str], ...] = (
    ("iou_prediction_head.layers.0", "iou_prediction_head.proj_in"),
    ("iou_prediction_head.layers.1", "iou_prediction_head.layers.0"),
    ("iou_prediction_head.layers.2", "iou_prediction_head.proj_out"),
    ("mask_decoder.output_upscaling.0", "mask_decoder.upscale_conv1"),
    ("mask_decoder.output_upscaling.1", "mask_decoder.upscale_layer_norm"),
    ("mask_decoder.output_upscaling.3", "mask_decoder.upscale_conv2"),
    ("mask_downscaling.0", "mask_embed.conv1"),
    ("mask_downscaling.1", "mask_embed.layer_norm1"),
    ("mask_downscaling.3", "mask_embed.conv2"),
    ("mask_downscaling.4", "mask_embed.layer_norm2"),
    ("mask_downscaling.6", "mask_embed.conv3"),
    ("point_embeddings", "point_embed"),
    ("pe_layer.positional_encoding_gaussian_matrix", "shared_embedding.positional_embedding"),
    ("image_encoder", "vision_encoder"),
    ("neck.0", "neck.conv1"),
    ("neck.1", "neck.layer_norm1"),
    ("neck.2", "neck.conv2"),
    ("neck.3", "neck.layer_norm2"),
    ("patch_embed.proj", "patch_embed.projection"),
    (".norm", ".layer_norm"),
    ("blocks", "layers"),
)
_HYPER = re.compile(r"(.*output_hypernetworks_mlps\.\d+\.)layers\.(\d+)(.*)")
# Attention heads are not visible in the weights: the published widths' head counts.
_HEADS_BY_WIDTH = {768: 12, 1024: 16, 1280: 16}


def convert_original_state_dict(state: Mapping[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    """Rename an original segment-anything state dict to ``transformers.SamModel`` keys."""
    out: dict[str, torch.Tensor] = {}
    for key, value in state.items():
        if key in ("pixel_mean", "pixel_std"):
            continue
        for old, new in _RENAMES:
            if old in key:
                key = key.replace(old, new)
        m = _HYPER.match(key)
        if m:
            layer = int(m.group(2))
            key = m.group(1) + {0: "proj_in", 1: "layers.0", 2: "proj_out"}.get(layer, f"layers.{layer - 1}") + m.group(3)
        out[key] = value
    pe = out.get("prompt_encoder.shared_embedding.positional_embedding")
    if pe is not None:
        out["shared_image_embedding.positional_embedding"] = pe
    return out


def infer_original_config(state: Mapping[str, torch.Tensor], vision_overrides: Mapping[str, Any] | None = None):
    """A ``transformers.SamConfig`` matching an original checkpoint's tensors."""
    transformers = require("transformers", purpose="loading SAM")

    def get(key: str) -> torch.Tensor:
        if key not in state:
            raise ValueError(f"tiger: the SAM checkpoint has no tensor '{key}'; is it an original segment-anything .pth?")
        return state[key]

    proj = get("image_encoder.patch_embed.proj.weight")
    hidden, patch = proj.shape[0], proj.shape[-1]
    grid = get("image_encoder.pos_embed").shape[1]
    depth = 1 + max(int(k.split(".")[2]) for k in state if k.startswith("image_encoder.blocks."))
    full_rel = 2 * grid - 1
    global_idx, window = [], 14
    for i in range(depth):
        n = get(f"image_encoder.blocks.{i}.attn.rel_pos_h").shape[0]
        if n == full_rel:
            global_idx.append(i)
        else:
            window = (n + 1) // 2
    vision = dict(
        hidden_size=hidden,
        patch_size=patch,
        image_size=grid * patch,
        num_hidden_layers=depth,
        num_attention_heads=_HEADS_BY_WIDTH.get(hidden, max(1, hidden // 64)),
        mlp_dim=get("image_encoder.blocks.0.mlp.lin1.weight").shape[0],
        output_channels=get("image_encoder.neck.0.weight").shape[0],
        global_attn_indexes=global_idx,
        window_size=window,
        num_pos_feats=get("prompt_encoder.pe_layer.positional_encoding_gaussian_matrix").shape[1],
    )
    vision.update(vision_overrides or {})
    dec_hidden = get("mask_decoder.iou_token.weight").shape[1]
    dec_layers = 1 + max(int(k.split(".")[3]) for k in state if k.startswith("mask_decoder.transformer.layers."))
    prompt = dict(hidden_size=dec_hidden, image_size=grid * patch, patch_size=patch,
                  mask_input_channels=get("prompt_encoder.mask_downscaling.3.weight").shape[0])
    decoder = dict(
        hidden_size=dec_hidden,
        num_hidden_layers=dec_layers,
        mlp_dim=get("mask_decoder.transformer.layers.0.mlp.lin1.weight").shape[0],
        num_multimask_outputs=get("mask_decoder.mask_tokens.weight").shape[0] - 1,
        iou_head_hidden_dim=get("mask_decoder.iou_prediction_head.layers.0.weight").shape[0],
    )
    return transformers.SamConfig(vision_config=vision, prompt_encoder_config=prompt, mask_decoder_config=decoder)


def load_sam(
    path: PathLike | None = None,
    *,
    device: str | torch.device = "cpu",
    dtype: torch.dtype = torch.float32,
    config: ConfigLike = None,
    allow_download: bool = False,
    vision_overrides: Mapping[str, Any] | None = None,
):
    """Load SAM as a ``transformers.SamModel`` (eval mode), offline.

    ``path`` is a ``save_pretrained`` folder (``config.json`` + ``model.safetensors``) or an
    original segment-anything checkpoint (``sam_vit_h_4b8939.pth``). ``vision_overrides``
    fixes what an original checkpoint cannot tell (its attention head count, for
    non-published widths).
    """
    found = resolve_model_path("sam", path, config=config, allow_download=allow_download)
    transformers = require("transformers", purpose="loading SAM")
    if found.is_file():
        state = torch.load(str(found), map_location="cpu", weights_only=True)
        if isinstance(state, Mapping) and "model" in state and "image_encoder.pos_embed" not in state:
            state = state["model"]
        cfg = infer_original_config(state, vision_overrides)
        model = transformers.SamModel(cfg)
        missing, unexpected = model.load_state_dict(convert_original_state_dict(state), strict=False)
        missing = [k for k in missing if not k.endswith("position_ids")]
        if missing or unexpected:
            raise ValueError(
                f"tiger: the SAM checkpoint {found} does not match the SAM architecture: "
                f"missing {missing[:8]}{'...' if len(missing) > 8 else ''}, unexpected {unexpected[:8]}"
            )
        logger.info("loaded original SAM checkpoint %s (%d blocks, width %d)", found,
                    cfg.vision_config.num_hidden_layers, cfg.vision_config.hidden_size)
    else:
        model = transformers.SamModel.from_pretrained(str(found), local_files_only=True)
        logger.info("loaded SAM from %s", found)
    return model.to(device=device, dtype=dtype).eval()
