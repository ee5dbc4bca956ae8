"""3DGS reconstruction: fit a Gaussian scene to posed images (INRIA's recipe)."""
from __future__ import annotations

from .config import ReconConfig, expon_lr
from .data import load_views
from .losses import photometric_loss, psnr, ssim, ssim_map
from .step import SceneOptimizer, StepOutput
from .trainer import Trainer

__all__ = ["ReconConfig", "SceneOptimizer", "StepOutput", "Trainer", "expon_lr", "load_views", "photometric_loss", "psnr", "ssim", "ssim_map"]
