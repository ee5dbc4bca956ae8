"""``tiger::masked_average``: fake kernel, autograd, and the Python entry point.

Every pixel inside a mask takes the mean feature of its mask; pixels in no mask keep their
feature (SPEC §4, SAM aggregation). See ``csrc/masked_average/masked_average.h``.
"""
from __future__ import annotations

import torch

__all__ = ["masked_average"]


@torch.library.register_fake("tiger::masked_average")
def _fake(features: torch.Tensor, ids: torch.Tensor, num_masks: int):
    return (
        features.new_empty(features.shape),
        features.new_empty((num_masks, features.shape[1])),
        ids.new_empty((num_masks,)),
    )


@torch.library.register_fake("tiger::masked_average_backward")
def _fake_backward(grad_out, grad_means, ids, counts):
    return grad_out.new_empty(grad_out.shape)


def _setup_context(ctx, inputs, output):
    _, ids, _ = inputs
    ctx.save_for_backward(ids, output[2])


def _backward(ctx, grad_out, grad_means, _grad_counts):
    ids, counts = ctx.saved_tensors
    if grad_out is None and grad_means is None:
        return None, None, None
    if grad_out is None:
        grad_out = grad_means.new_zeros((ids.shape[0], grad_means.shape[1]))
    if grad_means is None:
        grad_means = grad_out.new_zeros((counts.shape[0], grad_out.shape[1]))
    grad = torch.ops.tiger.masked_average_backward(grad_out.contiguous(), grad_means.contiguous(), ids, counts)
    return grad, None, None


torch.library.register_autograd("tiger::masked_average", _backward, setup_context=_setup_context)


def masked_average(
    features: torch.Tensor, ids: torch.Tensor, num_masks: int | None = None
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Mean feature of each mask, scattered back to its pixels.

    Args:
        features: [P, C] float32/float64 per-pixel features (any P, e.g. H*W flattened).
        ids: [P] int64 mask id of each pixel in [0, M), or -1 for a pixel in no mask.
        num_masks: M; default ``ids.max() + 1``.

    Returns:
        (out [P, C], means [M, C], counts [M] int64): ``out[p] = means[ids[p]]`` where
        ``ids[p] >= 0`` else ``features[p]``; an empty mask has mean 0. Differentiable in
        ``features`` (through ``out`` and ``means``).
    """
    if num_masks is None:
        num_masks = int(ids.max().item()) + 1 if ids.numel() else 0
    return torch.ops.tiger.masked_average(features, ids.to(torch.int64), int(num_masks))
