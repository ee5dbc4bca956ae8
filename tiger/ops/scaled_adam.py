"""``tiger::scaled_adam_``: one Adam step of several tensors, each row's update scaled by a weight
(TIGER's relevance-scaled update, paper §3.3), optionally written into the rows of the full tensors
the optimised rows came from. :class:`tiger.recon.SceneOptimizer` steps every trainable subset of a
scene with it (the edit's weighted rows, a deletion refit's region). Kernels in ``csrc/scaled_adam/``.

Adam as ``torch.optim.Adam`` computes it (no weight decay, no amsgrad); with weight ``w`` of row
``r`` the parameter moves by ``w_r`` times Adam's update, ``p <- p + w_r (p_adam - p)``; the moments
are not scaled. On CUDA the whole step is two launches (the step counts, then one thread per
element of every tensor), where ``torch.optim.Adam(fused=True)`` plus the scaling and the scatter
into the scene took ~30 launches for an edit's few hundred thousand elements.
"""
from __future__ import annotations

from typing import Optional, Sequence

import torch
from torch import Tensor

__all__ = ["scaled_adam_"]


@torch.library.register_fake("tiger::scaled_adam_")
def _fake(params, grads, exp_avgs, exp_avg_sqs, steps, lrs, beta1, beta2, eps, weight=None, targets=(), index=None):
    return None


def scaled_adam_(params: Sequence[Tensor], grads: Sequence[Tensor], exp_avgs: Sequence[Tensor],
                 exp_avg_sqs: Sequence[Tensor], steps: Sequence[Tensor], lrs: Sequence[float],
                 betas: tuple[float, float] = (0.9, 0.999), eps: float = 1e-8, weight: Optional[Tensor] = None,
                 targets: Sequence[Tensor] = (), index: Optional[Tensor] = None) -> None:
    """One in-place Adam step of ``params`` with the update of row ``r`` scaled by ``weight[r]``.

    Args:
        params: K (1-8) contiguous float32/float64 tensors [M, ...], one device, M rows each.
        grads, exp_avgs, exp_avg_sqs: K tensors of the params' shapes (Adam's moments, updated).
        steps: K one-element float tensors on the params' device: Adam's step counts, incremented
            by one, then used for the bias corrections (as ``torch.optim.Adam``'s ``state["step"]``).
        lrs: K learning rates.
        betas, eps: Adam's.
        weight: [M] factor on each row's update (None: 1, plain Adam).
        targets, index: with ``index`` [M] int64, the updated row ``r`` of ``params[k]`` is also
            written to row ``index[r]`` of ``targets[k]`` [N, ...] (the full tensor the rows came
            from). Indices are checked on the CPU only.

    Shape:
        - params[k], grads[k], exp_avgs[k], exp_avg_sqs[k]: :math:`(M, *)`
        - weight, index: :math:`(M)`; targets[k]: :math:`(N, *)` with params[k]'s row shape.

    Example:
        >>> p, g = torch.zeros(2, 1), torch.ones(2, 1)
        >>> m, v, t = torch.zeros(2, 1), torch.zeros(2, 1), torch.zeros(())
        >>> scaled_adam_([p], [g], [m], [v], [t], [0.1], weight=torch.tensor([1.0, 0.5]))
        >>> [round(x, 4) for x in p.flatten().tolist()], float(t)
        ([-0.1, -0.05], 1.0)
    """
    torch.ops.tiger.scaled_adam_(list(params), list(grads), list(exp_avgs), list(exp_avg_sqs), list(steps),
                                 [float(x) for x in lrs], float(betas[0]), float(betas[1]), float(eps), weight,
                                 list(targets), index)
