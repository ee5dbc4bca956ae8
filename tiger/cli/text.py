"""Text encoders for the query commands: CLIP from weights, or a table of embeddings."""
from __future__ import annotations

from typing import Optional

import torch

from tiger.retrieval.text import EmbeddingTable, TextEncoder


def text_encoder(models: Optional[str], table: Optional[str], device: torch.device) -> TextEncoder:
    """CLIP text tower (MaskCLIP templates) from --models/$TIGER_MODELS, or --text-embeddings."""
    if table:
        return EmbeddingTable.load(table)
    from tiger.language.maskclip import MaskCLIP

    return MaskCLIP.from_pretrained(device=device, config=models)
