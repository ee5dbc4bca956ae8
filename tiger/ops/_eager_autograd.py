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

    class _Fn(torch.autograd.Function):
        @staticmethod
        def forward(*args: Any) -> Any:
            with torch._C._AutoDispatchBelowAutograd():
                return op(*args)

        @staticmethod
        def setup_context(ctx: Any, inputs: tuple, output: Any) -> None:
            setup_context(ctx, inputs, output)

        @staticmethod
        def backward(ctx: Any, *grads: Any) -> tuple:
            return backward(ctx, *grads)

    _Fn.__name__ = _Fn.__qualname__ = f"{op._qualified_op_name.replace('::', '_')}_eager"

    def call(*args: Any) -> Any:
        if torch.compiler.is_compiling():  # traced: the registered op and formula
            return op(*args)
        if torch.is_grad_enabled() and any(isinstance(a, torch.Tensor) and a.requires_grad
                                           for a in args):
            return _Fn.apply(*args)
        with torch._C._AutoDispatchBelowAutograd():  # nothing to record: the kernel alone
            return op(*args)

    return call
