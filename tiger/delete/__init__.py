"""Deleting a retrieved object (paper appendix; SPEC §6): remove it, inpaint the views, refit the hole.

``tiger.delete.delete(scene, target, cameras)`` runs the pipeline (:mod:`.pipeline`) with a
:class:`DeleteConfig` and returns a :class:`DeleteResult` (:mod:`.config`). Its parts: which
Gaussians go (:mod:`.removal`), the hole masks (:mod:`.holes`), the inpainters (:mod:`.inpaint`),
the seed Gaussians placed in the holes (:mod:`.seeds`) and the refit on the inpainted views
(:mod:`.refit`, on :mod:`tiger.train`). Evaluation is not part of the call:
:func:`tiger.eval.reprojection.evaluate_delete` measures a result (as ``tiger delete`` does).
"""
from .config import DeleteConfig, DeleteResult
from .inpaint import Inpainter, LamaInpainter, OpenCVInpainter, make_inpainter
from .pipeline import delete, views_around

# refit stays in tiger.delete.refit (a function named like its module is not re-exported: it would hide it)
__all__ = ["DeleteConfig", "DeleteResult", "Inpainter", "LamaInpainter", "OpenCVInpainter", "delete", "make_inpainter",
           "views_around"]
