"""Model loading: where weights are found (``paths``) and loaders for CLIP, SAM and FeatUp's
JBU upsampler. Heavy libraries (transformers) are imported only when a loader runs."""
from __future__ import annotations

from .paths import ENV_VAR, REGISTRY, ModelNotFoundError, ModelSpec, resolve_model_path

__all__ = [
    "ENV_VAR",
    "REGISTRY",
    "ModelNotFoundError",
    "ModelSpec",
    "resolve_model_path",
    "load_clip",
    "load_sam",
    "load_jbu_checkpoint",
]


def __getattr__(name: str):
    if name == "load_clip":
        from .clip import load_clip

        return load_clip
    if name == "load_sam":
        from .sam import load_sam

        return load_sam
    if name == "load_jbu_checkpoint":
        from .featup import load_jbu_checkpoint

        return load_jbu_checkpoint
    raise AttributeError(name)
