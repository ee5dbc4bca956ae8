"""CLIP ViT-B/16 (``openai/clip-vit-base-patch16``) from a Hugging Face ``save_pretrained`` folder."""
from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Any

import torch

from tiger.utils.lazy import require

from .paths import ConfigLike, PathLike, resolve_model_path

logger = logging.getLogger(__name__)


@dataclass
class CLIPBundle:
    """A CLIP model (``transformers.CLIPModel``, eval mode) and its tokenizer."""

    model: Any
    tokenizer: Any


def load_clip(
    path: PathLike | None = None,
    *,
    device: str | torch.device = "cpu",
    dtype: torch.dtype = torch.float32,
    config: ConfigLike = None,
    allow_download: bool = False,
) -> CLIPBundle:
    """Load CLIP (model + tokenizer) from a ``save_pretrained`` folder, offline.

    The folder holds ``config.json``, ``model.safetensors`` (or ``pytorch_model.bin``) and the
    tokenizer files (``vocab.json`` + ``merges.txt``, or ``tokenizer.json``).
    """
    folder = resolve_model_path("clip", path, config=config, allow_download=allow_download)
    transformers = require("transformers", purpose="loading CLIP")
    model = transformers.CLIPModel.from_pretrained(str(folder), local_files_only=True)
    model = model.to(device=device, dtype=dtype).eval()
    tokenizer = _load_tokenizer(transformers, folder)
    logger.info("loaded CLIP from %s (%d vision layers)", folder, model.config.vision_config.num_hidden_layers)
    return CLIPBundle(model=model, tokenizer=tokenizer)


def _load_tokenizer(transformers: Any, folder) -> Any:
    errors = []
    for cls_name in ("CLIPTokenizer", "CLIPTokenizerFast", "AutoTokenizer"):
        cls = getattr(transformers, cls_name, None)
        if cls is None:
            continue
        try:
            return cls.from_pretrained(str(folder), local_files_only=True)
        except Exception as exc:  # noqa: BLE001 - try the next tokenizer class, report all below
            errors.append(f"{cls_name}: {exc}")
    raise OSError(f"tiger: cannot load the CLIP tokenizer from {folder}: " + "; ".join(errors))
