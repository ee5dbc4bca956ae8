"""The built-in demo: a procedural tabletop scene, rendered, language-embedded and queried."""
from .scene import LabelledGaussians, orbit_viewmats, pinhole_K, tabletop_scene

__all__ = ["LabelledGaussians", "tabletop_scene", "orbit_viewmats", "pinhole_K"]
