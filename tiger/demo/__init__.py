"""The built-in demo: a procedural tabletop scene, rendered, language-embedded and queried."""
from .scene import orbit_cameras, orbit_viewmats, pinhole_K, tabletop_scene

__all__ = ["tabletop_scene", "orbit_viewmats", "orbit_cameras", "pinhole_K"]
