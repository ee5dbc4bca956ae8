"""Rendering: cameras, the public rasterizer and its float64 dense reference."""
from .camera import Camera, Distortion
from .rasterize import RasterSettings, camera_center, rasterize_gaussians, sh_colors

__all__ = ["rasterize_gaussians", "RasterSettings", "camera_center", "sh_colors", "Camera", "Distortion"]
