"""Editing and deletion of retrieved objects (paper §3.2 and appendix; SPEC §6).

``tiger.edit.edit(scene, target, guidance)`` runs Coherent Score Distillation on the retrieved
Gaussians only (the guidance carries the instruction); guidances live in :mod:`tiger.edit.guidance` (``RecolorGuidance`` needs no
weights), object-centred cameras in :mod:`tiger.edit.views`. ``tiger.edit.delete(scene, target,
cameras)`` removes an object, inpaints the views (:mod:`tiger.edit.inpaint`) and refits the hole.
"""
from .config import DEFAULT_EDIT_LRS, EditConfig
from .csd import CSDGuidance, CSDSchedule
from .delete import DeleteConfig, DeleteResult, delete, views_around
from .inpaint import Inpainter, LamaInpainter, OpenCVInpainter, make_inpainter
from .loop import EditResult, EditSession, edit
from .target import EditTarget, EmptyTargetError, resolve_target
from .views import ObjectViews, capture_layout

__all__ = ["CSDGuidance", "CSDSchedule", "DEFAULT_EDIT_LRS", "DeleteConfig", "DeleteResult", "Inpainter",
           "LamaInpainter", "OpenCVInpainter", "delete", "make_inpainter", "views_around", "EditConfig", "EditResult", "EditSession",
           "EditTarget", "EmptyTargetError", "ObjectViews", "capture_layout", "edit", "resolve_target"]
