"""Guidance modules: each turns rendered views into a gradient on those renders.

The edit loop only sees :class:`~tiger.edit.guidance.base.Guidance`; the models behind a
guidance (diffusion UNets, VAEs, text encoders) stay inside it. Built in without weights:
:class:`RecolorGuidance` (``recolor``) and, for tests, :class:`IdealDenoiserGuidance`.
"""
from .analytic import IdealDenoiserGuidance, render_targets
from .base import Guidance, GuidanceInfo, ViewBatch
from .recolor import RecolorGuidance, parse_color

__all__ = ["Guidance", "GuidanceInfo", "IdealDenoiserGuidance", "RecolorGuidance", "ViewBatch", "parse_color",
           "render_targets"]
