"""One way to give a model's submodules another forward and take it back (the model kernels'
switches: :mod:`.model_kernels`, :mod:`.encoder_bias`)."""
from __future__ import annotations

import types
from typing import Callable

import torch

__all__ = ["switch_forward"]


def switch_forward(model: torch.nn.Module, eligible: Callable[[torch.nn.Module], bool], forward: Callable,
                   on: bool) -> int:
    """Give every submodule of ``model`` that ``eligible`` accepts the instance method ``forward``
    (``on``), or its class's forward again (off); returns how many have ``forward`` afterwards."""
    count = 0
    for m in model.modules():
        if not eligible(m):
            continue
        if on:
            m.forward = types.MethodType(forward, m)
            count += 1
        else:
            m.__dict__.pop("forward", None)
    return count
