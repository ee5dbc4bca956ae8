"""The featup op family: ``tiger::jittered_window_attention`` (FeatUp's attention downsampler
over jittered copies of one feature map, without materialising the copies),
``tiger::fourier_layer_norm`` (the implicit network's Fourier features, LayerNorm and channel
dropout in one pass), ``tiger::relu_scale_layer_norm`` (its hidden ReLU, channel dropout and
LayerNorm in one pass), ``tiger::magnitude_blur`` (the fit's per-pixel magnitude and reflect
Gaussian blur, channels last) and ``tiger::masked_logit`` (the attention logit of every pixel
after the input dropout, channels last): fake kernels, autograd and the Python entry points.
Formulas in ``csrc/featup/featup.h``, ``fourier.h``, ``relu_norm.h``, ``magnitude_blur.h`` and
``masked_logit.h``."""
from __future__ import annotations

from typing import Optional

import torch

from ._eager_autograd import eager_autograd

__all__ = ["jittered_window_attention", "WINDOW_VARIANTS", "fourier_layer_norm", "relu_scale_layer_norm",
           "magnitude_blur", "masked_logit"]


# The CUDA kernel variants of tiger::jittered_window_attention (csrc/featup/featup.h), each adding
# to the one before: the same function up to float rounding ("staged_tiles_bf16": the features
# read as bfloat16). The CPU kernels are the reference of every variant.
WINDOW_VARIANTS = ("baseline", "shared_scatter", "pixel_dots", "staged_tiles", "staged_tiles_bf16")


@torch.library.register_fake("tiger::jittered_window_attention")
def _fake(features, logit_map, coord_y, coord_x, w, b, mask, stride_h, stride_w, variant="baseline"):
    torch._check(features.dim() == 3, lambda: f"features must be [H, W, C], got {tuple(features.shape)}")
    torch._check(mask.dim() == 3, lambda: f"mask must be [J, FH, FW], got {tuple(mask.shape)}")
    torch._check(w.dim() == 2, lambda: f"w must be [K, K], got {tuple(w.shape)}")
    j, fh, fw = mask.shape
    return features.new_empty((j, fh, fw, features.shape[2])), features.new_empty((j, fh, fw, w.shape[0] * w.shape[1]))


@torch.library.register_fake("tiger::jittered_window_attention_backward")
def _fake_backward(grad_out, features, logit_map, coord_y, coord_x, w, b, mask, attn, stride_h, stride_w,
                   variant="baseline"):
    torch._check(grad_out.shape[-1] == features.shape[-1], lambda: "grad_out must be [J, FH, FW, C]")
    return (features.new_empty(features.shape), logit_map.new_empty(logit_map.shape), w.new_empty(w.shape),
            b.new_empty(b.shape))


def _setup_context(ctx, inputs, output):
    features, logit_map, coord_y, coord_x, w, b, mask, stride_h, stride_w, variant = inputs
    ctx.save_for_backward(features, logit_map, coord_y, coord_x, w, b, mask, output[1])
    ctx.strides = (stride_h, stride_w)
    ctx.variant = variant
    ctx.mark_non_differentiable(output[1])


def _backward(ctx, grad_out, _grad_attn):
    features, logit_map, coord_y, coord_x, w, b, mask, attn = ctx.saved_tensors
    needs = ctx.needs_input_grad
    if grad_out is None or not (needs[0] or needs[1] or needs[4] or needs[5]):
        return (None,) * 10
    gf, gl, gw, gb = torch.ops.tiger.jittered_window_attention_backward(
        grad_out.contiguous(), features, logit_map, coord_y, coord_x, w, b, mask, attn, *ctx.strides, ctx.variant)
    return (gf if needs[0] else None, gl if needs[1] else None, None, None, gw if needs[4] else None,
            gb if needs[5] else None, None, None, None, None)


torch.library.register_autograd("tiger::jittered_window_attention", _backward, setup_context=_setup_context)


def jittered_window_attention(features: torch.Tensor, logit_map: torch.Tensor, coord_y: torch.Tensor,
                              coord_x: torch.Tensor, w: torch.Tensor, b: torch.Tensor, mask: torch.Tensor,
                              stride: tuple[int, int], variant: str = "baseline") -> tuple[torch.Tensor, torch.Tensor]:
    """FeatUp's attention downsampler over J jittered copies of one map (float32/float64).

    Args:
        features: [H, W, C] the blurred high-resolution features, channels last.
        logit_map: [H, W] the attention logit of every source pixel.
        coord_y: [J, Ho] source row (pixels, in [0, H-1]: reflect beforehand) of each row of copy j.
        coord_x: [J, Wo] source column of each column of copy j.
        w, b: [K, K] logit scale and bias of the window softmax.
        mask: [J, FH, FW] logit multiplier per copy and cell (FeatUp's logit dropout; ones for none).
        stride: (rows, columns) between the windows of neighbouring cells.
        variant: the CUDA kernels (one of :data:`WINDOW_VARIANTS`, forward and backward; each
            adds to the one before): "baseline" (one block per cell, the logit map's gradient by
            K*K*4 global atomics per cell), "shared_scatter" (that gradient summed per cell in
            shared memory first: one global atomic per touched source pixel), "pixel_dots" (the
            backward's dots of the output gradient with the features pixel-major: each feature
            read once; C <= 10239 for float32), "staged_tiles" (the features' gradient reads the
            covering tiles from shared memory; the forward sums 4 neighbouring cells of a window
            row per block over the union of their tiles), "staged_tiles_bf16" (the attention's reads of the
            features from a bfloat16 copy, float32 accumulation; float32 only). The same function
            up to float rounding (bfloat16's for the last); the CPU computes the reference for
            every name.

    Returns:
        (out [J, FH, FW, C], attn [J, FH, FW, K*K]): the softmax-weighted window sums of the
        bilinearly resampled copies, and the softmax weights (not differentiable). ``out`` is
        differentiable in ``features``, ``logit_map``, ``w`` and ``b``.
    """
    return torch.ops.tiger.jittered_window_attention(features, logit_map, coord_y, coord_x, w, b, mask,
                                                     int(stride[0]), int(stride[1]), variant)


# ----------------------------------------------------------------------------- fourier_layer_norm
@torch.library.register_fake("tiger::fourier_layer_norm")
def _fourier_fake(inputs, freqs, phase, weight, bias, scale, eps, out_dtype):
    torch._check(inputs.dim() == 3 and inputs.shape[2] == 5, lambda: f"inputs must be [B, N, 5], got {tuple(inputs.shape)}")
    torch._check(freqs.dim() == 1, lambda: f"freqs must be [F], got {tuple(freqs.shape)}")
    b, n, _ = inputs.shape
    c = 10 * freqs.shape[0] + 3
    out = inputs.new_empty((b, n, c), dtype=out_dtype if out_dtype is not None else inputs.dtype)
    return out, inputs.new_empty((b, n)), inputs.new_empty((b, n))


@torch.library.register_fake("tiger::fourier_layer_norm_backward")
def _fourier_fake_backward(grad_out, inputs, freqs, phase, weight, scale, mean, rstd, input_grad):
    grad_inputs = inputs.new_empty(inputs.shape) if input_grad else inputs.new_empty((0,))
    return grad_inputs, phase.new_empty(phase.shape), weight.new_empty(weight.shape), weight.new_empty(weight.shape)


def _fourier_setup_context(ctx, inputs, output):
    inp, freqs, phase, weight, _bias, scale, _eps, _out_dtype = inputs
    _, mean, rstd = output
    ctx.save_for_backward(inp, freqs, phase, weight, scale, mean, rstd)
    ctx.mark_non_differentiable(mean, rstd)


def _fourier_backward(ctx, grad_out, _grad_mean, _grad_rstd):
    inp, freqs, phase, weight, scale, mean, rstd = ctx.saved_tensors
    needs = ctx.needs_input_grad
    if grad_out is None or not (needs[0] or needs[2] or needs[3] or needs[4]):
        return (None,) * 8
    gi, gp, gw, gb = torch.ops.tiger.fourier_layer_norm_backward(
        grad_out.contiguous(), inp, freqs, phase, weight, scale, mean, rstd, bool(needs[0]))
    return (gi if needs[0] else None, None, gp if needs[2] else None, gw if needs[3] else None,
            gb if needs[4] else None, None, None, None)


torch.library.register_autograd("tiger::fourier_layer_norm", _fourier_backward,
                                setup_context=_fourier_setup_context)
_fourier_eager = eager_autograd(torch.ops.tiger.fourier_layer_norm, _fourier_setup_context, _fourier_backward)


def fourier_layer_norm(inputs: torch.Tensor, freqs: torch.Tensor, phase: torch.Tensor, weight: torch.Tensor,
                       bias: torch.Tensor, scale: Optional[torch.Tensor] = None, eps: float = 1e-5,
                       out_dtype: Optional[torch.dtype] = None) -> torch.Tensor:
    """FeatUp's Fourier features of each pixel's (y, x, r, g, b), their LayerNorm and a per-image,
    per-channel multiplier, in one pass (``tiger::fourier_layer_norm``; formula in
    ``csrc/featup/fourier.h``). The backward recomputes the features from ``inputs``.

    Args:
        inputs: [B, N, 5] float32/float64, per pixel (y, x, r, g, b).
        freqs: [F] the frequencies (not differentiable).
        phase: [2, 5, F] learned phase biases, read as FeatUp reads them: channel c (< 10F) of the
            output adds ``phase.flatten()[c]``; sin channels first (c < 5F, c = 5 f + d), then cos.
        weight, bias: [C] the LayerNorm's affine, C = 10F + 3.
        scale: [B, C] multiplier per image and channel applied after the LayerNorm (the channel
            dropout's mask divided by the keep rate), or None; not differentiable.
        eps: added to the biased variance over the C channels.
        out_dtype: the output's dtype: None (the inputs'), torch.bfloat16 or torch.float16.

    Returns:
        [B, N, C]: channels (sin, cos of ``inputs[d] * freqs[f] + phase``, then r, g, b),
        LayerNormed over C, times ``scale``. Differentiable in inputs, phase, weight and bias.
    """
    if freqs.requires_grad or (scale is not None and scale.requires_grad):
        raise ValueError("tiger.fourier_layer_norm: freqs and scale are not differentiable; pass them detached")
    return _fourier_eager(inputs, freqs, phase, weight, bias, scale, float(eps), out_dtype)[0]


# ----------------------------------------------------------------------------- relu_scale_layer_norm
def _stat_dtype(x: torch.Tensor) -> torch.dtype:
    return torch.float64 if x.dtype == torch.float64 else torch.float32


@torch.library.register_fake("tiger::relu_scale_layer_norm")
def _relu_norm_fake(x, scale, weight, bias, eps):
    torch._check(x.dim() == 3, lambda: f"x must be [B, N, D], got {tuple(x.shape)}")
    b, n, _ = x.shape
    return torch.empty_like(x), x.new_empty((b, n), dtype=_stat_dtype(x)), x.new_empty((b, n), dtype=_stat_dtype(x))


@torch.library.register_fake("tiger::relu_scale_layer_norm_backward")
def _relu_norm_fake_backward(grad_out, x, scale, weight, mean, rstd):
    return torch.empty_like(x), weight.new_empty(weight.shape), weight.new_empty(weight.shape)


def _relu_norm_setup_context(ctx, inputs, output):
    x, scale, weight, _bias, _eps = inputs
    _, mean, rstd = output
    ctx.save_for_backward(x, scale, weight, mean, rstd)
    ctx.mark_non_differentiable(mean, rstd)


def _relu_norm_backward(ctx, grad_out, _grad_mean, _grad_rstd):
    x, scale, weight, mean, rstd = ctx.saved_tensors
    needs = ctx.needs_input_grad
    if grad_out is None or not (needs[0] or needs[2] or needs[3]):
        return (None,) * 5
    gx, gw, gb = torch.ops.tiger.relu_scale_layer_norm_backward(grad_out.contiguous(), x, scale, weight, mean, rstd)
    return gx if needs[0] else None, None, gw if needs[2] else None, gb if needs[3] else None, None


torch.library.register_autograd("tiger::relu_scale_layer_norm", _relu_norm_backward,
                                setup_context=_relu_norm_setup_context)
_relu_norm_eager = eager_autograd(torch.ops.tiger.relu_scale_layer_norm, _relu_norm_setup_context,
                                  _relu_norm_backward)


def relu_scale_layer_norm(x: torch.Tensor, weight: torch.Tensor, bias: torch.Tensor,
                          scale: Optional[torch.Tensor] = None, eps: float = 1e-5) -> torch.Tensor:
    """``layer_norm(relu(x) * scale)`` over the last dimension in one pass
    (``tiger::relu_scale_layer_norm``; formula in ``csrc/featup/relu_norm.h``), read and written
    in x's dtype with float32 statistics; the backward recomputes ``relu(x) * scale`` from x.

    Args:
        x: [B, N, D] float32/float64 (bfloat16/float16 too), e.g. a linear layer's output.
        weight, bias: [D] the LayerNorm's affine, float32 (float64 for float64 x).
        scale: [B, D] multiplier per image and channel (the channel dropout's mask divided by the
            keep rate; non-negative), same dtype as weight, or None; not differentiable.
        eps: added to the biased variance over the D channels.

    Returns:
        [B, N, D] in x's dtype. Differentiable in x, weight and bias.
    """
    if scale is not None and scale.requires_grad:
        raise ValueError("tiger.relu_scale_layer_norm: scale is not differentiable; pass it detached")
    return _relu_norm_eager(x, scale, weight, bias, float(eps))[0]


# ----------------------------------------------------------------------------- magnitude_blur
def _blur_out_dtype(x: torch.Tensor) -> torch.dtype:
    return torch.float64 if x.dtype == torch.float64 else torch.float32


@torch.library.register_fake("tiger::magnitude_blur")
def _magnitude_blur_fake(x, radius, sigma):
    torch._check(x.dim() == 3, lambda: f"x must be [H, W, C], got {tuple(x.shape)}")
    torch._check(0 <= radius < x.shape[0] and radius < x.shape[1],
                 lambda: f"reflect padding by radius {radius} needs H and W > radius, got x {tuple(x.shape)}")
    h, w, c = x.shape
    dt = _blur_out_dtype(x)
    return x.new_empty((h, w, c + 1), dtype=dt), x.new_empty((h, w), dtype=dt)


@torch.library.register_fake("tiger::magnitude_blur_backward")
def _magnitude_blur_fake_backward(grad_blurred, grad_magnitude, x, magnitude, radius, sigma):
    torch._check(grad_blurred.shape == (*x.shape[:2], x.shape[2] + 1),
                 lambda: f"grad_blurred must be [H, W, C + 1], got {tuple(grad_blurred.shape)}")
    return torch.empty_like(x)


def _magnitude_blur_setup_context(ctx, inputs, output):
    x, radius, sigma = inputs
    ctx.save_for_backward(x, output[1])
    ctx.blur = (radius, sigma)


def _magnitude_blur_backward(ctx, grad_blurred, grad_magnitude):
    x, magnitude = ctx.saved_tensors
    if not ctx.needs_input_grad[0] or (grad_blurred is None and grad_magnitude is None):
        return None, None, None
    if grad_blurred is None:
        grad_blurred = magnitude.new_zeros((*x.shape[:2], x.shape[2] + 1))
    grad_x = torch.ops.tiger.magnitude_blur_backward(
        grad_blurred.contiguous(), None if grad_magnitude is None else grad_magnitude.contiguous(), x, magnitude,
        *ctx.blur)
    return grad_x, None, None


torch.library.register_autograd("tiger::magnitude_blur", _magnitude_blur_backward,
                                setup_context=_magnitude_blur_setup_context)
_magnitude_blur_eager = eager_autograd(torch.ops.tiger.magnitude_blur, _magnitude_blur_setup_context,
                                       _magnitude_blur_backward)


def magnitude_blur(x: torch.Tensor, radius: int = 2, sigma: float = 1.0) -> tuple[torch.Tensor, torch.Tensor]:
    """Each pixel's feature magnitude, and the reflect-padded Gaussian blur of (magnitude,
    features), channels last in one op (``tiger::magnitude_blur``; formula in
    ``csrc/featup/magnitude_blur.h``): ``gaussian_blur(cat([x.norm(dim=1), x], 1), 2 * radius + 1,
    sigma, padding="reflect")`` for a channels-first x, without the channels-first copies.

    Args:
        x: [H, W, C] float32/float64 (bfloat16/float16 too, read as is and accumulated in
            float32), e.g. the implicit network's channels-last output; H, W > radius.
        radius: taps on each side (<= 8); FeatUp's fit blurs with 5 taps (radius 2), sigma 1.
        sigma: the Gaussian's standard deviation, pixels.

    Returns:
        (blurred [H, W, C + 1], magnitude [H, W]), float32 (float64 for float64 x); channel 0 of
        ``blurred`` is the blurred magnitude. Both differentiable in x.
    """
    return _magnitude_blur_eager(x, int(radius), float(sigma))


# ----------------------------------------------------------------------------- masked_logit
@torch.library.register_fake("tiger::masked_logit")
def _masked_logit_fake(x, keep, keep_scale, weight, bias):
    torch._check(x.dim() == 3, lambda: f"x must be [H, W, U], got {tuple(x.shape)}")
    torch._check(weight.shape == (x.shape[2],), lambda: f"weight must be [U] = [{x.shape[2]}], got {tuple(weight.shape)}")
    torch._check(keep is None or keep.shape == (x.shape[2], *x.shape[:2]),
                 lambda: f"keep must be [U, H, W], got {None if keep is None else tuple(keep.shape)}")
    return x.new_empty(x.shape[:2])


@torch.library.register_fake("tiger::masked_logit_backward")
def _masked_logit_fake_backward(grad, x, keep, keep_scale, weight, x_grad):
    torch._check(grad.shape == x.shape[:2], lambda: f"grad must be [H, W], got {tuple(grad.shape)}")
    return (torch.empty_like(x) if x_grad else x.new_empty((0,))), weight.new_empty(weight.shape), weight.new_empty((1,))


def _masked_logit_setup_context(ctx, inputs, output):
    x, keep, keep_scale, weight, _bias = inputs
    ctx.save_for_backward(x, keep, weight)
    ctx.keep_scale = keep_scale


def _masked_logit_backward(ctx, grad):
    x, keep, weight = ctx.saved_tensors
    needs = ctx.needs_input_grad
    if grad is None or not (needs[0] or needs[3] or needs[4]):
        return (None,) * 5
    gx, gw, gb = torch.ops.tiger.masked_logit_backward(grad.contiguous(), x, keep, ctx.keep_scale, weight,
                                                       bool(needs[0]))
    return gx if needs[0] else None, None, None, gw if needs[3] else None, gb if needs[4] else None


torch.library.register_autograd("tiger::masked_logit", _masked_logit_backward,
                                setup_context=_masked_logit_setup_context)
_masked_logit_eager = eager_autograd(torch.ops.tiger.masked_logit, _masked_logit_setup_context,
                                     _masked_logit_backward)


def masked_logit(x: torch.Tensor, weight: torch.Tensor, bias: torch.Tensor, keep: Optional[torch.Tensor] = None,
                 keep_scale: float = 1.0) -> torch.Tensor:
    """The attention logit of every pixel after the input dropout,
    ``bias + sum_k weight[k] x[..., k] m[k]`` with ``m = keep * keep_scale``
    (``tiger::masked_logit``; formula in ``csrc/featup/masked_logit.h``): the 1x1 convolution of
    the dropped-out channels-first map ``x.permute(2, 0, 1) * keep * keep_scale``, read channels
    last, with a 1-byte mask.

    Args:
        x: [H, W, U] float32/float64, channels last.
        weight: [U], bias: [1] the attention's Linear (x's dtype).
        keep: [U, H, W] bool, the input dropout's kept elements drawn channels first (as
            ``F.dropout`` draws them for a [1, U, H, W] map: ``bernoulli_(1 - p)``), or None (no
            dropout).
        keep_scale: the kept elements' multiplier, ``1 / (1 - p)``.

    Returns:
        [H, W] in x's dtype, differentiable in x, weight and bias.
    """
    return _masked_logit_eager(x, keep, float(keep_scale), weight, bias)
