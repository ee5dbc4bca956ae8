"""``tiger::rasterize``: tile-based alpha compositing (public function, fake kernels, autograd;
semantics in ``csrc/raster/raster.h``).

The backward picks the features-only kernel when no geometry input (means2d,
conics, opacities, depths) needs a gradient: language-field training then pays
for no geometry term at all. The CUDA kernels' choices (:class:`RasterKernelSettings`) are
arguments of the forward op, which its autograd formula hands to the backward ops.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Optional

import torch
from torch import Tensor

from tiger.ops._eager_autograd import eager_autograd

_OP = "tiger::rasterize"

__all__ = ["rasterize", "RasterKernelSettings", "TILE_ORDERS"]

TILE_ORDERS = ("index", "heavy_first")  # the ops' tile_order argument is the index (raster.h)


@dataclass(frozen=True)
class RasterKernelSettings:
    """Kernel choices of the CUDA rasterization (float32; float64 runs blocks of 8 channels, one
    pixel per thread, and the CPU kernels only check them). Every choice gives the same result up
    to float32 rounding. Defaults: the measured best on the H100 (docs/BENCHMARKS.md), the same
    as the op schemas' (``csrc/raster/raster.h``).

    Attributes:
        forward_channel_block, backward_channel_block, colors_channel_block: the largest
            channel block held in registers by the forward, the backward and the features-only
            backward kernel: 64 (a C <= 64 tile list is walked once) or 32.
        backward_pixels_per_thread: pixels per backward thread, 2 where they apply (16-px tiles,
            channel blocks of at most 16 channels) or 1.
        tile_order: the order the kernels draw tiles in: ``"heavy_first"`` (tiles with longer
            lists first, within a factor of sqrt 2, so that the longest walks do not run alone
            at the end of a kernel) or ``"index"``. The forward's values are the same bit for
            bit, the backward's up to the order of its atomic sums.
        warp_cull: each warp walks only the list entries whose cutoff ellipse may reach one of
            its pixel centres (an exact per-row test with a rounding margin): the values are the
            same bit for bit; ``False`` skips that test (comparisons; the backward walks still stop
            at the warp's largest ``n_contrib``, which needs no test).
    """

    forward_channel_block: int = 64
    backward_channel_block: int = 64
    colors_channel_block: int = 64
    backward_pixels_per_thread: int = 2
    tile_order: str = "heavy_first"
    warp_cull: bool = True

    def __post_init__(self) -> None:
        if self.tile_order not in TILE_ORDERS:
            raise ValueError(f"tiger.ops.raster: tile_order must be one of {TILE_ORDERS}, got {self.tile_order!r}")

    def op_args(self) -> tuple[int, int, int, int]:
        """The forward op's kernel arguments before ``views``, in schema order."""
        return (int(self.forward_channel_block), int(self.backward_channel_block),
                int(self.colors_channel_block), int(self.backward_pixels_per_thread))

    def tile_order_arg(self) -> int:
        """The ops' ``tile_order`` argument (their last): 0 index order, 1 heavy first."""
        return TILE_ORDERS.index(self.tile_order)

    def launch_args(self) -> tuple[int, bool]:
        """The ops' last two arguments, ``tile_order`` and ``warp_cull``."""
        return self.tile_order_arg(), bool(self.warp_cull)


_DEFAULT = RasterKernelSettings()
_N_GEOMETRY_ARGS = 6  # width, height, tile_size, alpha_max, alpha_threshold, t_min
_N_KERNEL_ARGS = 4  # RasterKernelSettings.op_args(); then the forward's views, trainable, tile_order, warp_cull


def rasterize(means2d: Tensor, conics: Tensor, opacities: Tensor, colors: Tensor, depths: Tensor,
              background: Optional[Tensor], tile_offsets: Tensor, gaussian_ids: Tensor, width: int,
              height: int, tile_size: int, alpha_max: float, alpha_threshold: float,
              t_min: float, kernels: RasterKernelSettings = _DEFAULT, views: int = 1,
              trainable: Optional[Tensor] = None) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
    """Composite projected Gaussians front to back, differentiably.

    Args:
        means2d: [N, 2] px; conics: [N, 3]; opacities: [N]; depths: [N] (from
            :func:`project_gaussians`); colors: [N, C] any C >= 1 (float16/bfloat16 with float32
            geometry on CUDA); background: [C] or None (zeros);
        tile_offsets, gaussian_ids: from :func:`bin_gaussians`; width, height, tile_size: px;
        alpha_max: per-Gaussian alpha clamp; alpha_threshold: smaller alphas are skipped;
        t_min: a pixel stops once its transmittance would drop below this.
        kernels: the CUDA kernels' choices, forward and backward (:class:`RasterKernelSettings`).
        views: V images of ``width`` x ``height`` drawn in one call from tile lists of
            :func:`bin_gaussians` with the same ``views`` (CPU and CUDA): every per-pixel
            output is [V * H, W(, C)], image v in rows v*H .. (v+1)*H - 1, each equal to a
            ``views=1`` call on its own Gaussians.
        trainable: optional bool [N] (N the stacked count): the Gaussians whose gradients the
            backward computes. Frozen ones still shape every pixel's transmittance, but get zero
            gradients and cost no gradient reduction or atomics on CUDA; the trainable ones'
            gradients equal the full backward's (on CUDA up to the atomics' summation order).
    Returns:
        color [H, W, C] = Σ c_i a_i T_i + T_final background, alpha [H, W] = 1 - T_final,
        depth_accum [H, W] = Σ z_i a_i T_i, n_contrib [H, W] int32 and transmittance [H, W]
        (T_final; both not differentiable, kept for the backward).
    """
    return _rasterize_eager(
        means2d, conics, opacities, colors, depths,
        background.contiguous() if background is not None else None, tile_offsets, gaussian_ids,
        int(width), int(height), int(tile_size), float(alpha_max), float(alpha_threshold),
        float(t_min), *kernels.op_args(), int(views), trainable, *kernels.launch_args())


def _check_channel_block(op: str, name: str, value: int) -> None:
    torch._check(value in (64, 32), lambda: f"{op}: {name} must be 64 or 32 (the compiled float32 "
                                            f"channel blocks), got {value}")


def _check_tile_order(op: str, value: int) -> None:
    torch._check(0 <= value < len(TILE_ORDERS), lambda: f"{op}: tile_order must be 0 (index order) or 1 "
                 f"(longest tile lists first), got {value}")


def _check_pixels_per_thread(op: str, name: str, value: int) -> None:
    torch._check(value in (1, 2), lambda: f"{op}: {name} must be 1 or 2, got {value}")


@torch.library.register_fake(_OP)
def _raster_fake(means2d, conics, opacities, colors, depths, background, tile_offsets,
                 gaussian_ids, width, height, tile_size, alpha_max, alpha_threshold, t_min,
                 channel_block=_DEFAULT.forward_channel_block,
                 backward_channel_block=_DEFAULT.backward_channel_block,
                 colors_channel_block=_DEFAULT.colors_channel_block,
                 backward_pixels_per_thread=_DEFAULT.backward_pixels_per_thread, views=1,
                 trainable=None, tile_order=_DEFAULT.tile_order_arg(), warp_cull=_DEFAULT.warp_cull):
    op = "tiger.rasterize"
    _check_channel_block(op, "channel_block", channel_block)
    _check_channel_block(op, "backward_channel_block", backward_channel_block)
    _check_channel_block(op, "colors_channel_block", colors_channel_block)
    _check_pixels_per_thread(op, "backward_pixels_per_thread", backward_pixels_per_thread)
    _check_tile_order(op, tile_order)
    # Outputs take the geometry dtype: colors may be stored in float16/bfloat16 (CUDA).
    c = colors.shape[1]
    rows = views * height  # the views' images, stacked
    return (means2d.new_empty(rows, width, c), means2d.new_empty(rows, width),
            means2d.new_empty(rows, width), means2d.new_empty(rows, width, dtype=torch.int32),
            means2d.new_empty(rows, width))


@torch.library.register_fake("tiger::rasterize_backward")
def _raster_backward_fake(means2d, conics, opacities, colors, depths, background, tile_offsets,
                          gaussian_ids, width, height, tile_size, alpha_max, alpha_threshold, t_min,
                          transmittance, n_contrib, v_color, v_alpha, v_depth,
                          channel_block=_DEFAULT.backward_channel_block,
                          pixels_per_thread=_DEFAULT.backward_pixels_per_thread, views=1,
                          trainable=None, tile_order=_DEFAULT.tile_order_arg(),
                          warp_cull=_DEFAULT.warp_cull):
    _check_channel_block("tiger.rasterize_backward", "channel_block", channel_block)
    _check_pixels_per_thread("tiger.rasterize_backward", "pixels_per_thread", pixels_per_thread)
    _check_tile_order("tiger.rasterize_backward", tile_order)
    return (means2d.new_empty(means2d.shape[0], 8), means2d.new_empty(colors.shape),
            means2d.new_empty(colors.shape[1]))


@torch.library.register_fake("tiger::rasterize_backward_colors")
def _raster_backward_colors_fake(means2d, conics, opacities, tile_offsets, gaussian_ids, width,
                                 height, tile_size, alpha_max, alpha_threshold, t_min, n_contrib,
                                 v_color, channel_block=_DEFAULT.colors_channel_block, views=1,
                                 trainable=None, tile_order=_DEFAULT.tile_order_arg(),
                                 warp_cull=_DEFAULT.warp_cull):
    _check_channel_block("tiger.rasterize_backward_colors", "channel_block", channel_block)
    _check_tile_order("tiger.rasterize_backward_colors", tile_order)
    c = v_color.shape[2]
    return means2d.new_empty(means2d.shape[0], c), means2d.new_empty(c)


def _setup(ctx: Any, inputs: tuple, output: tuple) -> None:
    (means2d, conics, opacities, colors, depths, background, tile_offsets, gaussian_ids,
     *args) = inputs
    _, _, _, n_contrib, transmittance = output
    # The kernel choices of the backward ops, views and trainable (a call without them: defaults).
    kernel_args = tuple(args[_N_GEOMETRY_ARGS:_N_GEOMETRY_ARGS + _N_KERNEL_ARGS])
    _, ctx.backward_channel_block, ctx.colors_channel_block, ctx.backward_pixels_per_thread = (
        kernel_args + _DEFAULT.op_args()[len(kernel_args):])
    extra = args[_N_GEOMETRY_ARGS + _N_KERNEL_ARGS:]
    ctx.views = extra[0] if len(extra) > 0 else 1
    trainable = extra[1] if len(extra) > 1 else None
    ctx.tile_order = extra[2] if len(extra) > 2 else _DEFAULT.tile_order_arg()
    ctx.warp_cull = extra[3] if len(extra) > 3 else _DEFAULT.warp_cull
    ctx.save_for_backward(means2d, conics, opacities, colors, depths, background, tile_offsets,
                          gaussian_ids, transmittance, n_contrib, trainable)
    ctx.args = tuple(args[:_N_GEOMETRY_ARGS])
    ctx.mark_non_differentiable(n_contrib, transmittance)
    # Unused outputs (alpha and depth in a colour-only loss) reach the backward as None, not as
    # [H, W] zero tensors filled for nothing; the kernel reads no gradient for them.
    ctx.set_materialize_grads(False)


def _backward(ctx: Any, v_color, v_alpha, v_depth, _v_count, _v_trans):
    (means2d, conics, opacities, colors, depths, background, tile_offsets, gaussian_ids, trans,
     n_contrib, trainable) = ctx.saved_tensors
    need = ctx.needs_input_grad
    if v_color is None:
        v_color = torch.zeros(trans.shape + colors.shape[1:], dtype=colors.dtype,
                              device=colors.device)
    geometry = need[0] or need[1] or need[2] or need[4]
    if not geometry:
        v_colors, v_bg = torch.ops.tiger.rasterize_backward_colors(
            means2d, conics, opacities, tile_offsets, gaussian_ids, *ctx.args, n_contrib,
            v_color.contiguous(), ctx.colors_channel_block, ctx.views, trainable, ctx.tile_order,
            ctx.warp_cull)
        v_colors = v_colors.to(colors.dtype)  # half-precision storage: grads in its dtype
        return (None, None, None, v_colors if need[3] else None, None,
                v_bg if need[5] else None) + (None,) * (len(need) - 6)
    g = torch.ops.tiger.rasterize_backward(
        means2d, conics, opacities, colors, depths, background, tile_offsets, gaussian_ids,
        *ctx.args, trans, n_contrib, v_color.contiguous(),
        None if v_alpha is None else v_alpha.contiguous(),
        None if v_depth is None else v_depth.contiguous(), ctx.backward_channel_block,
        ctx.backward_pixels_per_thread, ctx.views, trainable, ctx.tile_order, ctx.warp_cull)
    v_geom, v_colors, v_bg = g   # v_geom [N, 8]: u, v, conic a, b, c, opacity, depth, 0
    v_means2d, v_conics, v_opac, v_depths = v_geom[:, 0:2], v_geom[:, 2:5], v_geom[:, 5], v_geom[:, 6]
    v_colors = v_colors.to(colors.dtype)
    return (v_means2d if need[0] else None, v_conics if need[1] else None,
            v_opac if need[2] else None, v_colors if need[3] else None,
            v_depths if need[4] else None, v_bg if need[5] else None) + (None,) * (len(need) - 6)


torch.library.register_autograd(_OP, _backward, setup_context=_setup)
_rasterize_eager = eager_autograd(torch.ops.tiger.rasterize, _setup, _backward)
