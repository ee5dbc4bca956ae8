"""Lazy imports of heavy optional dependencies, with an install hint."""
from __future__ import annotations

import importlib
from types import ModuleType


def require(module: str, pip_name: str | None = None, purpose: str = "") -> ModuleType:
    """Import ``module`` or raise ImportError saying what to install and why."""
    try:
        return importlib.import_module(module)
    except ImportError as exc:
        why = f" (needed for {purpose})" if purpose else ""
        raise ImportError(
            f"tiger: the optional dependency '{module}' is not installed{why}; "
            f"install it with `pip install {pip_name or module}`"
        ) from exc


#: The diffusers release the guidances' model code is written against (read from its forward methods).
DIFFUSERS_PIN = "diffusers==0.42.*"


def require_diffusers(purpose: str) -> ModuleType:
    """Import diffusers (the diffusion guidances' models), or an ImportError with the install hint."""
    return require("diffusers", pip_name=DIFFUSERS_PIN, purpose=purpose)
