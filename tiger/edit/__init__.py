"""Editing of retrieved objects (paper §3.2 and appendix; SPEC §6).

``tiger.edit.edit(scene, target, guidance)`` runs Coherent Score Distillation on the retrieved
Gaussians only (the guidance carries the instruction); guidances live in :mod:`tiger.edit.guidance` (``RecolorGuidance`` needs no
weights), object-centred cameras in :mod:`tiger.edit.views`. Deleting an object is :mod:`tiger.delete`.
"""
from .config import DEFAULT_EDIT_LRS, EditConfig
from .csd import CSDGuidance, CSDSchedule
from .loop import EditResult, EditSession, edit
from .target import EditTarget, EmptyTargetError, resolve_target
from .views import ObjectViews, capture_layout

__all__ = ["CSDGuidance", "CSDSchedule", "DEFAULT_EDIT_LRS", "EditConfig", "EditResult", "EditSession",
           "EditTarget", "EmptyTargetError", "ObjectViews", "capture_layout", "edit", "resolve_target"]
