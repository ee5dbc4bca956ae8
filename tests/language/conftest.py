"""Tiny random CLIP and SAM (hidden 32, 2 layers, 64-pixel inputs) saved with ``save_pretrained``."""
import pytest

from tiger.testing.random_models import save_random_clip, save_random_sam


@pytest.fixture(scope="session")
def tiny_models(tmp_path_factory):
    root = tmp_path_factory.mktemp("tiny_models")
    save_random_clip(root / "clip-vit-base-patch16")
    save_random_sam(root / "sam-vit-huge")
    return root


@pytest.fixture(scope="session")
def maskclip(tiny_models):
    from tiger.language.maskclip import MaskCLIP

    return MaskCLIP.from_pretrained(tiny_models / "clip-vit-base-patch16")
