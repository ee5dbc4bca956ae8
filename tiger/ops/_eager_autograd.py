"""The eager entry of an op whose autograd formula is registered with ``torch.library``.

``torch.ops.tiger.<op>`` with inputs that require grad goes through torch.library's generated
autograd function, which rebuilds the op's argument list from its schema on every call
(``fill_defaults``: ~50 us per call on a CPU of the CI machine, as much as the rest of a tiny
render's Python together). The public functions of ``tiger.ops`` call the kernels through
:func:`eager_autograd` instead: an ``autograd.Function`` with the *same* ``setup_context`` and
``backward`` that were registered, dispatching below the autograd key. The registered path
stays what ``torch.ops.tiger.<op>``, ``opcheck`` and ``torch.compile`` use.
"""
from __future__ import annotations

from typing import Any, Callable

import torch


def eager_autograd(op: torch._ops.OpOverloadPacket, setup_context: Callable[..., None],
                   backward: Callable[..., tuple]) -> Callable[..., Any]:
    """``op``'s positional-argument call with the given autograd formula (one per op)."""

    # forward(ctx, ...) rather than a setup_context staticmethod: with one, every apply()
    # binds the arguments to forward's signature through inspect (~20 us).
    def forward(ctx: Any, *args: Any) -> Any:
        with torch._C._AutoDispatchBelowAutograd():
            output = op(*args)
        setup_context(ctx, args, output)
        return output

    def function_backward(ctx: Any, *grads: Any) -> tuple:
        return backward(ctx, *grads)

    # Named after the op, so that profiles and graphs show e.g. tiger_rasterize_eagerBackward.
    name = f"{op._qualified_op_name.replace('::', '_')}_eager"
    _Fn = type(name, (torch.autograd.Function,), {"forward": staticmethod(forward),
                                                   "backward": staticmethod(function_backward)})

    def call(*args: Any) -> Any:
        if torch.compiler.is_compiling() or torch._C._are_functorch_transforms_active():
            return op(*args)  # traced or transformed: the registered op and formula
        if torch.is_grad_enabled() and any(isinstance(a, torch.Tensor) and a.requires_grad
                                           for a in args):
            return _Fn.apply(*args)
        with torch._C._AutoDispatchBelowAutograd():  # nothing to record: the kernel alone
            return op(*args)

    return call
