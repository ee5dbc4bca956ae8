"""Language features (SPEC §4): MaskCLIP, FeatUp, SAM finest masks, masked average, PCA, and the
``extract_features`` pipeline. Submodules are imported on first use, so importing this package
stays cheap (no transformers at import time)."""
from __future__ import annotations

import importlib

_EXPORTS = {
    "extract_features": "extract",
    "FeatureConfig": "extract",
    "FeatureSet": "extract",
    "read_rgb_image": "extract",
    "MaskCLIP": "maskclip",
    "SamMaskGenerator": "sam_masks",
    "SamMaskConfig": "sam_masks",
    "SamMasks": "sam_masks",
    "JBUStack": "featup",
    "ImplicitUpsampler": "featup",
    "ImplicitConfig": "featup",
    "upsample_features": "featup",
    "PCABasis": "pca",
    "StreamingPCA": "pca",
    "train_field": "field",
    "FieldConfig": "field",
    "FieldResult": "field",
}

__all__ = sorted(_EXPORTS)


def __getattr__(name: str):
    if name in _EXPORTS:
        return getattr(importlib.import_module(f"{__name__}.{_EXPORTS[name]}"), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
