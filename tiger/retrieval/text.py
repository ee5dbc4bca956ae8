"""Text queries -> unit vectors in the scene's language space.

A query is a string (or strings), encoded by a text encoder with ``encode_text(texts) -> [Q, F]``
(the CLIP text tower with prompt templates averaged, ``tiger.language``), then projected with the
scene's PCA, ``(e - mean) @ basis`` ([F] and [F, D]), then normalised. Precomputed embeddings of
either size (F: projected; D: used as they are) skip the encoder, so retrieval works and is
testable without CLIP weights.
"""
from __future__ import annotations

from typing import Any, Optional, Protocol, Sequence, Union

import torch

#: LERF's canonical negative phrases for the relevancy score.
CANONICAL_NEGATIVES: tuple[str, ...] = ("object", "things", "stuff", "texture")

Query = Union[str, Sequence[str], torch.Tensor]


class TextEncoder(Protocol):
    """Anything with ``encode_text(texts) -> [Q, F]`` (CLIP space, templates averaged)."""

    def encode_text(self, texts: Sequence[str]) -> torch.Tensor: ...


def pca_of(source: Any) -> Optional[tuple[torch.Tensor, torch.Tensor]]:
    """The (basis [F, D], mean [F]) PCA pair of a scene, a PCA object or a tuple; None if absent.

    Accepts a scene with ``lang_pca_basis``/``lang_pca_mean``, a ``tiger.language.PCABasis``
    (``components``/``mean``), an object with ``basis``/``mean``, a ``(basis, mean)`` tuple, or a
    dict with keys ``basis`` and ``mean``.
    """
    if source is None:
        return None
    if isinstance(source, (tuple, list)) and len(source) == 2:
        basis, mean = source
    elif isinstance(source, dict):
        basis, mean = source.get("basis"), source.get("mean")
    elif hasattr(source, "lang_pca_basis"):
        basis, mean = source.lang_pca_basis, getattr(source, "lang_pca_mean", None)
    elif hasattr(source, "components"):  # tiger.language.PCABasis
        basis, mean = source.components, getattr(source, "mean", None)
    elif hasattr(source, "basis"):
        basis, mean = source.basis, getattr(source, "mean", None)
    else:
        raise TypeError(f"tiger.retrieval: cannot read a PCA basis from {type(source).__name__}")
    if basis is None:
        return None
    basis = torch.as_tensor(basis)
    if basis.dim() != 2:
        raise ValueError(f"tiger.retrieval: PCA basis must be [F, D], got {list(basis.shape)}")
    mean = torch.zeros(basis.shape[0], dtype=basis.dtype) if mean is None else torch.as_tensor(mean)
    if mean.shape != (basis.shape[0],):
        raise ValueError(f"tiger.retrieval: PCA mean must be [F={basis.shape[0]}], got {list(mean.shape)}")
    return basis, mean


def project(embeddings: torch.Tensor, basis: torch.Tensor, mean: torch.Tensor) -> torch.Tensor:
    """[Q, F] CLIP embeddings -> [Q, D] unit vectors: ``normalize((e - mean) @ basis)``."""
    if embeddings.dim() != 2 or embeddings.shape[1] != basis.shape[0]:
        raise ValueError(f"tiger.retrieval: embeddings must be [Q, F={basis.shape[0]}] to project, "
                         f"got {list(embeddings.shape)}")
    e = embeddings.to(torch.float64)
    out = (e - mean.to(e)) @ basis.to(e)
    return torch.nn.functional.normalize(out, dim=1).to(torch.float32)


def embed_queries(query: Query, *, dim: int, encoder: Optional[TextEncoder] = None,
                  pca: Any = None) -> torch.Tensor:
    """Text or embeddings -> [Q, dim] float32 unit vectors in the language space.

    Args:
        query: a string, a sequence of strings, or an embedding tensor [F] / [Q, F] (CLIP space,
            projected with ``pca``) or [dim] / [Q, dim] (already in the language space).
        dim: the language space's dimension D (64 in TIGER).
        encoder: needed for strings (``encode_text``).
        pca: the scene (or PCA pair) whose basis projects CLIP embeddings; see :func:`pca_of`.
    """
    pair = pca_of(pca)
    if isinstance(query, str) or (isinstance(query, (list, tuple)) and query and
                                  all(isinstance(q, str) for q in query)):
        texts = [query] if isinstance(query, str) else list(query)
        if encoder is None:
            raise ValueError(f"tiger.retrieval: the text query {texts!r} needs a text encoder "
                             "(an object with encode_text), or pass a precomputed embedding")
        emb = torch.as_tensor(encoder.encode_text(texts)).detach().float().cpu()
        if emb.dim() != 2 or emb.shape[0] != len(texts):
            raise ValueError(f"tiger.retrieval: encode_text returned {list(emb.shape)} for {len(texts)} texts")
    else:
        emb = torch.as_tensor(query).detach().float().cpu()
        if emb.dim() == 1:
            emb = emb[None]
        if emb.dim() != 2:
            raise ValueError(f"tiger.retrieval: a query embedding must be [F] or [Q, F], got {list(emb.shape)}")
    if not torch.isfinite(emb).all():
        raise ValueError("tiger.retrieval: the query embedding has NaN or Inf values")
    if emb.shape[1] == dim and (pair is None or pair[0].shape[0] != dim):
        return torch.nn.functional.normalize(emb, dim=1)
    if pair is None:
        raise ValueError(f"tiger.retrieval: the query embedding has {emb.shape[1]} dims but the language "
                         f"space has {dim}, and no PCA basis was given to project it")
    if pair[0].shape[1] != dim:
        raise ValueError(f"tiger.retrieval: the PCA basis maps to {pair[0].shape[1]} dims, the language "
                         f"features have {dim}")
    return project(emb, *pair)


def embed_negatives(negatives: Union[None, Sequence[str], torch.Tensor], *, dim: int,
                    encoder: Optional[TextEncoder] = None, pca: Any = None) -> torch.Tensor:
    """The canonical negatives ([M, dim]); ``None`` -> an empty [0, dim] (cosine only).

    Strings need ``encoder``; tensors are treated like query embeddings.
    """
    if negatives is None:
        return torch.zeros(0, dim)
    if isinstance(negatives, (list, tuple)) and len(negatives) == 0:
        return torch.zeros(0, dim)
    return embed_queries(negatives, dim=dim, encoder=encoder, pca=pca)
