"""``tiger::group_norm``: GroupNorm with an optional fused SiLU (fake kernels, autograd, the
function and the module). Formulas in ``csrc/group_norm/group_norm.h``.

The CUDA kernels work on channels-last (NHWC) memory natively and return channels-last
output, so a channels-last diffusion model keeps its layout through its norms (PyTorch's CUDA
GroupNorm copies channels-last input to NCHW and returns NCHW). Statistics are float32
(float64 for float64 input on the CPU), combined with Welford/Chan merges in a fixed order.
The backward recomputes the SiLU's pre-activation from x and the saved mean/rstd, so nothing
beyond x is stored, and computes weight/bias gradients only when they are needed.
"""
from __future__ import annotations

from typing import Optional

import torch

from ._layout import output_format

__all__ = ["group_norm", "group_norm_with_stats", "group_norm_input_grad", "GroupNormSiLU"]


def _stat_dtype(x: torch.Tensor) -> torch.dtype:
    return torch.float64 if x.dtype == torch.float64 else torch.float32


@torch.library.register_fake("tiger::group_norm")
def _fake(x, weight, bias, num_groups, eps, silu, input_bias=None):
    stats = x.new_empty((x.shape[0], num_groups), dtype=_stat_dtype(x))
    return torch.empty_like(x, memory_format=output_format(x)), stats, stats.new_empty(stats.shape)


@torch.library.register_fake("tiger::group_norm_backward")
def _fake_backward(grad_y, x, weight, bias, mean, rstd, num_groups, silu, param_grads, input_bias=None,
                   residual_grad=None):
    c = x.shape[1] if param_grads else 0
    return (torch.empty_like(x, memory_format=output_format(x)), x.new_empty((c,), dtype=_stat_dtype(x)),
            x.new_empty((c,), dtype=_stat_dtype(x)))


def _setup_context(ctx, inputs, output):
    x, weight, bias, num_groups, _eps, silu = inputs[:6]
    input_bias = inputs[6] if len(inputs) > 6 else None
    _, mean, rstd = output
    ctx.save_for_backward(x, weight, bias, mean, rstd, input_bias)
    ctx.num_groups, ctx.silu = num_groups, silu
    ctx.mark_non_differentiable(mean, rstd)


def _backward(ctx, grad_y, _grad_mean, _grad_rstd):
    x, weight, bias, mean, rstd, input_bias = ctx.saved_tensors
    need = tuple(ctx.needs_input_grad) + (False,)
    need_x, need_w, need_b, need_ib = need[0], need[1], need[2], need[6]
    n_inputs = len(ctx.needs_input_grad)
    if grad_y is None or not (need_x or need_w or need_b or need_ib):
        return (None,) * n_inputs
    param_grads = bool(need_w or need_b)
    gx, gw, gb = torch.ops.tiger.group_norm_backward(grad_y, x, weight, bias, mean, rstd, ctx.num_groups,
                                                     ctx.silu, param_grads, input_bias)
    gw = gw.to(weight.dtype) if need_w else None
    gb = gb.to(bias.dtype) if need_b else None
    gib = None
    if need_ib:  # x + ib: the input bias's gradient is dx summed over each channel's pixels
        acc = torch.float64 if gx.dtype == torch.float64 else torch.float32
        gib = gx.sum(dim=(2, 3), dtype=acc)
        gib = (gib if input_bias.dim() == 2 else gib.sum(0)).to(input_bias.dtype)
    return ((gx if need_x else None), gw, gb, None, None, None, gib)[:n_inputs]


torch.library.register_autograd("tiger::group_norm", _backward, setup_context=_setup_context)


def group_norm(x: torch.Tensor, num_groups: int, weight: Optional[torch.Tensor] = None,
               bias: Optional[torch.Tensor] = None, eps: float = 1e-5, silu: bool = False,
               input_bias: Optional[torch.Tensor] = None) -> torch.Tensor:
    """GroupNorm of ``x`` (+ ``input_bias``), optionally followed by SiLU, in one pass.

    Args:
        x: [N, C, H, W] float32/bfloat16/float16 (float64 on the CPU); channels-last or NCHW.
        num_groups: G, dividing C.
        weight, bias: [C] per-channel affine (x's dtype or float32), or None (1 and 0).
        eps: added to the biased per-group variance.
        silu: apply ``z·sigmoid(z)`` to the normalised, affine-transformed value.
        input_bias: [C] or [N, C], added to x per (sample,) channel before the norm without being
            written out: a bias-free convolution's bias (plus a ResNet block's time embedding)
            folded into the norm that follows it. Computed in float32 (float64 for float64 x).

    Returns:
        [N, C, H, W] in x's dtype: ``act((x − mean_ng)·rstd_ng·w_c + b_c)`` with mean and the
        biased variance over each (n, group)'s C/G·H·W elements; channels-last when x is
        channels-last (and not also contiguous), else contiguous.
    """
    if input_bias is None:
        return torch.ops.tiger.group_norm(x, weight, bias, int(num_groups), float(eps), bool(silu))[0]
    return torch.ops.tiger.group_norm(x, weight, bias, int(num_groups), float(eps), bool(silu), input_bias)[0]


def group_norm_with_stats(x: torch.Tensor, num_groups: int, weight: Optional[torch.Tensor] = None,
                          bias: Optional[torch.Tensor] = None, eps: float = 1e-5, silu: bool = False,
                          input_bias: Optional[torch.Tensor] = None
                          ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """:func:`group_norm` that also returns the statistics a hand-written backward needs
    (:func:`group_norm_input_grad`): (y, mean [N, G], rstd [N, G]), float32 statistics (float64
    for float64 x). Meant for code that runs its own backward (no autograd through the stats)."""
    return torch.ops.tiger.group_norm(x, weight, bias, int(num_groups), float(eps), bool(silu), input_bias)


def group_norm_input_grad(grad_y: torch.Tensor, x: torch.Tensor, num_groups: int, mean: torch.Tensor,
                          rstd: torch.Tensor, weight: Optional[torch.Tensor] = None,
                          bias: Optional[torch.Tensor] = None, silu: bool = False,
                          input_bias: Optional[torch.Tensor] = None,
                          residual_grad: Optional[torch.Tensor] = None) -> torch.Tensor:
    """dL/dx of :func:`group_norm` (weights frozen: no parameter gradients), plus ``residual_grad``.

    Args:
        grad_y: [N, C, H, W] dL/dy, x's dtype.
        x, num_groups, weight, bias, silu, input_bias: as given to the forward.
        mean, rstd: [N, G] from :func:`group_norm_with_stats`.
        residual_grad: optional [N, C, H, W] (x's dtype): a gradient x receives through another
            path (a ResNet block's shortcut), added in the same pass before dx is rounded, instead
            of autograd's separate sum.

    Returns:
        [N, C, H, W] in x's dtype and layout.
    """
    return torch.ops.tiger.group_norm_backward(grad_y, x, weight, bias, mean, rstd, int(num_groups), bool(silu),
                                               False, input_bias, residual_grad)[0]


class GroupNormSiLU(torch.nn.Module):
    """``torch.nn.GroupNorm`` (+ SiLU when ``silu``) through :func:`group_norm`.

    Parameters ``weight``/``bias`` [C] keep nn.GroupNorm's names (state dicts are unchanged).
    Input [N, C, H, W], or [N, C, L] (run as [N, C, L, 1]: diffusers' attention blocks pass
    their [N, L, C] tokens transposed, which is channels-last in that view).
    """

    def __init__(self, num_groups: int, num_channels: int, eps: float = 1e-5, affine: bool = True,
                 silu: bool = False, device: Optional[torch.device] = None, dtype: Optional[torch.dtype] = None) -> None:
        super().__init__()
        if num_channels % num_groups != 0:
            raise ValueError(f"tiger.GroupNormSiLU: num_channels={num_channels} is not divisible by "
                             f"num_groups={num_groups}")
        self.num_groups, self.num_channels, self.eps, self.affine, self.silu = (
            int(num_groups), int(num_channels), float(eps), bool(affine), bool(silu))
        if affine:
            self.weight = torch.nn.Parameter(torch.ones(num_channels, device=device, dtype=dtype))
            self.bias = torch.nn.Parameter(torch.zeros(num_channels, device=device, dtype=dtype))
        else:
            self.register_parameter("weight", None)
            self.register_parameter("bias", None)

    @classmethod
    def from_group_norm(cls, gn: torch.nn.GroupNorm, silu: bool) -> "GroupNormSiLU":
        """The same norm (sharing ``gn``'s parameter objects) with SiLU fused when ``silu``."""
        m = cls.__new__(cls)
        torch.nn.Module.__init__(m)
        m.num_groups, m.num_channels, m.eps, m.affine, m.silu = (
            gn.num_groups, gn.num_channels, float(gn.eps), gn.affine, bool(silu))
        m.weight, m.bias = gn.weight, gn.bias
        m.train(gn.training)
        return m

    def forward(self, x: torch.Tensor, input_bias: Optional[torch.Tensor] = None) -> torch.Tensor:
        """``input_bias`` ([C] or [N, C]): added to x first (:func:`group_norm`)."""
        if x.dim() == 3:
            return group_norm(x.unsqueeze(-1), self.num_groups, self.weight, self.bias, self.eps, self.silu,
                              input_bias).squeeze(-1)
        return group_norm(x, self.num_groups, self.weight, self.bias, self.eps, self.silu, input_bias)

    def extra_repr(self) -> str:
        return (f"{self.num_groups}, {self.num_channels}, eps={self.eps}, affine={self.affine}, "
                f"silu={self.silu}")
