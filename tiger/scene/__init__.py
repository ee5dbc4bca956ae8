"""Scenes in and out: Gaussian scenes, their files, cameras and posed-image datasets."""
from __future__ import annotations

from .cameras import scene_extent
from .errors import MissingImagesError, SceneFormatError
from .gaussian_scene import (DEFAULT_LRS, PARAM_NAMES, ColorSpec, GaussianScene, read_ply, render_rgb,
                             render_view_chunks, render_views, write_ply)
from .labelled import LabelledScene

__all__ = ["GaussianScene", "MissingImagesError", "SceneFormatError", "DEFAULT_LRS",
           "PARAM_NAMES", "read_ply", "write_ply", "scene_extent", "render_views", "render_view_chunks", "render_rgb",
           "ColorSpec",
           "LabelledScene"]
