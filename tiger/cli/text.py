"""Text encoders for the query commands: CLIP from weights, or a table of embeddings."""
from __future__ import annotations

from typing import Optional

import torch


class TableEncoder:
    """``encode_text`` from a ``torch.save``'d {text: [F] tensor} file (no CLIP needed)."""

    def __init__(self, path: str) -> None:
        table = torch.load(path, map_location="cpu", weights_only=True)
        if not isinstance(table, dict) or not table:
            raise ValueError(f"{path}: expected a non-empty {{text: [F] tensor}} mapping")
        self.table = {str(k): torch.as_tensor(v, dtype=torch.float32) for k, v in table.items()}

    def encode_text(self, texts):
        missing = [t for t in texts if t not in self.table]
        if missing:
            raise ValueError(f"no embedding for {missing} in the text-embedding table "
                             f"(it has {sorted(self.table)[:20]})")
        return torch.stack([self.table[t] for t in texts])


def text_encoder(models: Optional[str], table: Optional[str], device: torch.device):
    """CLIP text tower (MaskCLIP templates) from --models/$TIGER_MODELS, or --text-embeddings."""
    if table:
        return TableEncoder(table)
    from tiger.language.maskclip import MaskCLIP

    return MaskCLIP.from_pretrained(device=device, config=models)
