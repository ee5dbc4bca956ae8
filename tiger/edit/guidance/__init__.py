"""Guidance modules: each turns rendered views into a gradient on those renders.

The edit loop and ``tiger edit`` only see the :class:`~tiger.edit.guidance.base.Guidance` protocol
(name, instruction, grad, settings, generators, reset_caches; optionally prepare); the models behind a guidance
(diffusion UNets, VAEs, text encoders) stay inside it. diffusers and transformers are imported
only when a model is loaded or built.

- :class:`InstructPix2PixGuidance` (``ip2p``): 2D instruction-edit SDS on any number of views.
- :class:`MVDreamGuidance` (``mvdream``): multi-view SDS on exactly 4 views (loads lazily).
- :class:`RecolorGuidance` (``recolor``): no weights; the object's pixels pulled toward a colour.

The known-answer guidance of the tests (the ideal denoiser) is
:class:`tiger.testing.ideal_denoiser.IdealDenoiserGuidance`.
"""
from .base import Guidance, GuidanceInfo, ViewBatch
from .ip2p import InstructPix2PixGuidance, IP2PModels, load_ip2p
from .mvdream import MVDreamGuidance, MVDreamModels, load_mvdream
from .recolor import RecolorGuidance, parse_color

__all__ = ["Guidance", "GuidanceInfo", "ViewBatch", "InstructPix2PixGuidance", "IP2PModels", "load_ip2p",
           "MVDreamGuidance", "MVDreamModels", "load_mvdream", "RecolorGuidance",
           "parse_color"]
