"""Text queries -> unit vectors in the scene's language space.

A query is a string (or strings), encoded by a text encoder with ``encode_text(texts) -> [Q, F]``
(the CLIP text tower with prompt templates averaged, ``tiger.language``), then projected with the
scene's PCA, ``(e - mean) @ basis`` ([F] and [F, D]), then normalised. Precomputed embeddings of
either size (F: projected; D: used as they are) skip the encoder, so retrieval works and is
testable without CLIP weights.
"""
from __future__ import annotations

import os
from pathlib import Path
from typing import TYPE_CHECKING, Mapping, Optional, Protocol, Sequence, Union

import torch

from tiger.utils.io import atomic_torch_save

if TYPE_CHECKING:
    from tiger.scene import GaussianScene

#: LERF's canonical negative phrases for the relevancy score.
CANONICAL_NEGATIVES: tuple[str, ...] = ("object", "things", "stuff", "texture")

Query = Union[str, Sequence[str], torch.Tensor]


class TextEncoder(Protocol):
    """Anything with ``encode_text(texts) -> [Q, F]`` (CLIP space, templates averaged)."""

    def encode_text(self, texts: Sequence[str]) -> torch.Tensor: ...


class PCAComponents(Protocol):
    """A fitted PCA (``tiger.language.PCABasis``): ``components`` [F, D] and ``mean`` [F]."""

    components: torch.Tensor
    mean: torch.Tensor


#: Where a PCA basis can be read from (see :func:`pca_of`).
PCASource = Union[None, "GaussianScene", PCAComponents, tuple[torch.Tensor, torch.Tensor],
                  Mapping[str, torch.Tensor]]


class UnknownTextError(KeyError, ValueError):
    """A text that an :class:`EmbeddingTable` has no embedding for (a KeyError and a ValueError)."""

    def __str__(self) -> str:
        return str(self.args[0]) if self.args else ""


class EmbeddingTable:
    """A text encoder over a fixed table ``{text: [F] embedding}``: ``encode_text`` looks up.

    Stands in for CLIP wherever embeddings were computed elsewhere (``--text-embeddings``
    files) or are made up (synthetic scenes, the demo without CLIP weights).

    Args:
        table: text -> embedding (any shape with F elements; stored as float32 [F]).
        source: how errors name the table (e.g. its file).
        fold_case: look texts up lower-cased and stripped (the table's keys are folded too).
        hint: appended to the error for an unknown text.
    """

    def __init__(self, table: Mapping[str, torch.Tensor], *, source: str = "the text-embedding table",
                 fold_case: bool = False, hint: str = "") -> None:
        if not table:
            raise ValueError(f"tiger: {source} is empty: expected {{text: [F] tensor}}")
        self.source, self.fold_case, self.hint = source, fold_case, hint
        self.table: dict[str, torch.Tensor] = {}
        for k, v in table.items():
            if not isinstance(k, str) or not torch.is_tensor(v):
                raise ValueError(f"tiger: {source} must map texts to tensors, got "
                                 f"{type(k).__name__} -> {type(v).__name__}")
            self.table[self._key(k)] = v.detach().to(torch.float32).reshape(-1)
        sizes = {v.shape[0] for v in self.table.values()}
        if len(sizes) != 1:
            raise ValueError(f"tiger: {source} mixes embedding sizes {sorted(sizes)}")

    def _key(self, text: str) -> str:
        return _fold(text) if self.fold_case else text

    def _lookup(self, text: str) -> Optional[str]:
        """The table key for ``text``: itself, else the one key equal to it up to case and spaces."""
        key = self._key(text)
        if key in self.table:
            return key
        matches = [k for k in self.table if _fold(k) == _fold(text)]
        return matches[0] if len(matches) == 1 else None

    @classmethod
    def load(cls, path: Union[str, os.PathLike], *, fold_case: bool = False,
             hint: str = "") -> "EmbeddingTable":
        """Read a ``torch.save``-d ``{text: [F] tensor}`` file (a ValueError naming the file when it
        is missing or not such a file)."""
        if not Path(path).is_file():
            raise FileNotFoundError(f"tiger: text-embedding table {path} does not exist")
        try:
            d = torch.load(str(path), map_location="cpu", weights_only=True)
        except Exception as exc:  # pickle/zip raise many types on foreign or corrupt files
            reason = " ".join(str(exc).split())[:120]
            raise ValueError(f"tiger: {path} is not a torch.save'd {{text: [F] tensor}} table "
                             f"({type(exc).__name__}: {reason})") from None
        if not isinstance(d, dict):
            raise ValueError(f"tiger: {path} must hold a dict {{text: [F] tensor}}, got {type(d).__name__}")
        return cls(d, source=str(path), fold_case=fold_case, hint=hint)

    def save(self, path: Union[str, os.PathLike]) -> Path:
        """Write the table as a ``torch.save``-d dict, atomically (what :meth:`load` reads)."""
        atomic_torch_save(dict(self.table), path)
        return Path(path)

    def __contains__(self, text: str) -> bool:
        return self._lookup(text) is not None

    def encode_text(self, texts: Sequence[str]) -> torch.Tensor:
        """[Q, F] float32 embeddings of ``texts``, looked up exactly, else ignoring case and
        surrounding spaces; an unknown text raises :class:`UnknownTextError` listing the table's
        texts (the first :data:`LISTED_TEXTS`, then how many more)."""
        keys = [self._lookup(t) for t in texts]
        missing = [_shorten(t) for t, k in zip(texts, keys) if k is None]
        if missing:
            names = sorted(self.table)
            listed = ", ".join(repr(_shorten(n)) for n in names[:LISTED_TEXTS])
            more = f" and {len(names) - LISTED_TEXTS} more" if len(names) > LISTED_TEXTS else ""
            raise UnknownTextError(f"no embedding for {missing} in {self.source} (its {len(names)} texts: "
                                   f"{listed}{more}){self.hint}")
        return torch.stack([self.table[k] for k in keys])


#: How many of a table's texts an unknown-text error lists; longer texts are cut at SHOWN_CHARS.
LISTED_TEXTS, SHOWN_CHARS = 60, 60


def _fold(text: str) -> str:
    return " ".join(text.lower().split())


def _shorten(text: str) -> str:
    """``text`` for a message: at most SHOWN_CHARS characters, saying how long it was."""
    return text if len(text) <= SHOWN_CHARS else f"{text[:SHOWN_CHARS]}... ({len(text)} characters)"


def pca_of(source: PCASource) -> Optional[tuple[torch.Tensor, torch.Tensor]]:
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
                  pca: PCASource = None) -> torch.Tensor:
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
                    encoder: Optional[TextEncoder] = None, pca: PCASource = None) -> torch.Tensor:
    """The canonical negatives ([M, dim]); ``None`` -> an empty [0, dim] (cosine only).

    Strings need ``encoder``; tensors are treated like query embeddings.
    """
    if negatives is None:
        return torch.zeros(0, dim)
    if isinstance(negatives, (list, tuple)) and len(negatives) == 0:
        return torch.zeros(0, dim)
    return embed_queries(negatives, dim=dim, encoder=encoder, pca=pca)
