"""TIGER: text-instructed retrieval and editing of 3D Gaussian Splatting scenes.

Importing the package loads the compiled core (``tiger._C``), which registers the
custom ops under ``torch.ops.tiger``, and their autograd and fake kernels.
"""
from __future__ import annotations

import torch  # noqa: F401  (loads libtorch before the extension)

from . import ops  # noqa: F401  (registers torch.ops.tiger.*)
from .render import rasterize_gaussians

__version__ = "0.1.0"
__all__ = ["rasterize_gaussians", "__version__"]
