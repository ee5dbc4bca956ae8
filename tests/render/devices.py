"""Devices the rendering tests run on: CPU always, CUDA when a GPU and the CUDA build exist."""
from __future__ import annotations

import pytest
import torch

import tiger.ops


def cuda_available() -> bool:
    return torch.cuda.is_available() and tiger.ops.cuda_enabled()


CUDA_SKIP = pytest.mark.skipif(not cuda_available(),
                               reason="needs a CUDA device and tiger built with CUDA")
CUDA = [pytest.mark.cuda, CUDA_SKIP]
DEVICES = [pytest.param("cpu", id="cpu"), pytest.param("cuda", id="cuda", marks=CUDA)]


def to(device: str, *tensors: torch.Tensor) -> list[torch.Tensor]:
    return [t.to(device) for t in tensors]
