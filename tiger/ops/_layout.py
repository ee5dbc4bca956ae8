"""The layout rule shared by the ops that keep channels-last maps channels-last (their fake
kernels must give the real kernels' strides): ``csrc/common/memory_format.h``."""
from __future__ import annotations

import torch


def output_format(x: torch.Tensor) -> torch.memory_format:
    """Channels-last when ``x`` is channels-last and not also contiguous, else contiguous NCHW."""
    if not x.is_contiguous() and x.is_contiguous(memory_format=torch.channels_last):
        return torch.channels_last
    return torch.contiguous_format
