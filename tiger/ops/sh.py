"""Fake kernel and autograd of ``tiger::sh_to_color``."""
from __future__ import annotations

from typing import Any

import torch

_OP = "tiger::sh_to_color"


@torch.library.register_fake(_OP)
def _sh_fake(dirs, coeffs, degree, visible):
    return dirs.new_empty(dirs.shape[0], 3)


@torch.library.register_fake("tiger::sh_to_color_backward")
def _sh_backward_fake(dirs, coeffs, degree, visible, v_colors):
    return torch.empty_like(dirs), torch.empty_like(coeffs)


def _setup(ctx: Any, inputs: tuple, output: torch.Tensor) -> None:
    dirs, coeffs, degree, visible = inputs
    ctx.save_for_backward(dirs, coeffs, visible)
    ctx.degree = degree


def _backward(ctx: Any, v_colors: torch.Tensor):
    dirs, coeffs, visible = ctx.saved_tensors
    v_dirs, v_coeffs = torch.ops.tiger.sh_to_color_backward(
        dirs, coeffs, ctx.degree, visible, v_colors.contiguous())
    need = ctx.needs_input_grad
    return (v_dirs if need[0] else None, v_coeffs if need[1] else None, None, None)


torch.library.register_autograd(_OP, _backward, setup_context=_setup)
