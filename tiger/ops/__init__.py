"""Custom ops in ``torch.ops.tiger``: loads the compiled library and registers, for
each op family (one module here per ``csrc/<family>/`` folder), its fake kernels
and autograd formulas through ``torch.library``.

Every submodule of this package is imported automatically, so a new op family
only adds ``tiger/ops/<family>.py``.
"""
from __future__ import annotations

import importlib
import pkgutil

import torch

try:
    from tiger import _C  # noqa: F401  (static TORCH_LIBRARY registration)
except ImportError as exc:  # pragma: no cover - only without a build
    raise ImportError(
        "tiger's compiled core (tiger._C) is missing or failed to load: build it with "
        "`make build` or `pip install --no-build-isolation -e .` "
        f"(original error: {exc})"
    ) from exc


def cuda_enabled() -> bool:
    """True when the compiled core contains the CUDA kernels."""
    return bool(_C.cuda_enabled())


for _mod in sorted(m.name for m in pkgutil.iter_modules(__path__)):
    if not _mod.startswith("_"):
        importlib.import_module(f"{__name__}.{_mod}")

__all__ = ["cuda_enabled"]
