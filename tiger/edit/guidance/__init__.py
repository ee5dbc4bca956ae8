"""Guidance modules: each turns rendered views into a gradient on those renders.

The edit loop only sees :class:`~tiger.edit.guidance.base.Guidance`; the models behind a
guidance (diffusion UNets, VAEs, text encoders) stay inside it.
"""
from .base import Guidance, GuidanceInfo, ViewBatch

__all__ = ["Guidance", "GuidanceInfo", "ViewBatch"]
