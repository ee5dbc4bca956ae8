"""Rendering: the public rasterizer and its float64 dense reference."""
from .rasterize import RasterDefaults, camera_center, rasterize_gaussians

__all__ = ["rasterize_gaussians", "RasterDefaults", "camera_center"]
