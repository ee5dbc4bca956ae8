"""Short dtype names, as the command line and the benchmarks spell them."""
from __future__ import annotations

import torch

__all__ = ["DTYPE_NAMES"]

DTYPE_NAMES: dict[str, torch.dtype] = {"fp32": torch.float32, "fp16": torch.float16, "bf16": torch.bfloat16}
