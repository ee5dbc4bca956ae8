"""The built-in demo: a procedural tabletop scene, rendered, language-embedded and queried."""
from .scene import DEMO_ORBIT, tabletop_scene

__all__ = ["DEMO_ORBIT", "tabletop_scene"]
