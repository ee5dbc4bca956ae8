"""Text encoders for the query commands: CLIP from weights, or a table of embeddings."""
from __future__ import annotations

from typing import TYPE_CHECKING, Optional

import torch

from tiger.retrieval.text import EmbeddingTable, TextEncoder

from .common import CliError

if TYPE_CHECKING:
    from tiger.scene import GaussianScene

#: CLIP ViT-B/16's embedding size: what the text tower returns.
CLIP_DIM = 512


def text_encoder(models: Optional[str], table: Optional[str], device: torch.device,
                 scene: Optional["GaussianScene"] = None, scene_file: Optional[str] = None) -> TextEncoder:
    """CLIP text tower (MaskCLIP templates) from --models/$TIGER_MODELS, or --text-embeddings.

    With ``scene``/``scene_file``: refuses, naming the missing ``<scene>.lang_pca.npz`` sidecar, when
    the encoder's embeddings need the scene's PCA basis to reach its language space and the basis
    is absent (the PLY was copied without its sidecar).
    """
    if table:
        enc: TextEncoder = EmbeddingTable.load(table)
        dim = next(iter(enc.table.values())).shape[0]
    else:
        from tiger.language.maskclip import MaskCLIP

        enc, dim = MaskCLIP.from_pretrained(device=device, config=models), CLIP_DIM
    if scene is not None:
        check_language_basis(scene, scene_file, dim)
    return enc


def check_language_basis(scene: "GaussianScene", scene_file: Optional[str], text_dim: int) -> None:
    """A CliError naming the PCA sidecar when ``text_dim``-d text embeddings cannot be projected
    into ``scene``'s language space for want of it."""
    if scene.lang is None or scene.lang_pca_basis is not None or text_dim == scene.lang.shape[1]:
        return
    from tiger.scene.ply import lang_pca_path

    side = lang_pca_path(scene_file) if scene_file else "<scene>.lang_pca.npz"
    raise CliError(f"{scene_file or 'the scene'} has {scene.lang.shape[1]}-d language features but no PCA "
                   f"basis to project {text_dim}-d text embeddings: its sidecar {side} is missing (it is "
                   "written beside the PLY; copy it along)")
