"""Cross-attention keys and values of a guidance's fixed text, computed once
(:class:`~tiger.edit.guidance.model_kernels.ModelKernels` field ``cached_text_kv``).

An edit's prompts never change, yet every UNet call projected the same text rows to the keys and
values of its 16 cross-attentions (InstructPix2Pix: 16 matmuls of 12·77 rows a call; MVDream: 32
of 8·77). With ``cached_text_kv`` the projections are kept on the text tensor itself (a memo per
layer), and the guidances pass the same text tensor every call (:func:`branch_text`): the first
call computes them, later calls and the CUDA graphs captured after it read them. The memo is
checked against the text's and the projection weights' identities and version counters (an in-place
change recomputes), lives exactly as long as the text tensor (which the guidance keeps as long as
its graphs), and is never written during a CUDA-graph capture (a capture without an eager call
before it computes its own inside the graph, whose memory other graphs may reuse). With gradients
enabled nothing is cached. The same matmuls on the same rows: the same values.
"""
from __future__ import annotations

from typing import Callable, Optional, Sequence

import torch

from .cuda_graph import capturing

__all__ = ["branch_text", "memo_text_kv"]

_MEMO = "_tiger_text_kv"
_ROWS = "_tiger_branch_text"


def memo_text_kv(layer: object, text: torch.Tensor, weights: Sequence[Optional[torch.Tensor]],
                 compute: Callable[[], tuple[torch.Tensor, torch.Tensor]],
                 keep: bool = True) -> tuple[torch.Tensor, torch.Tensor]:
    """``compute()`` (the keys and values of ``layer`` for ``text``), kept on ``text`` for the next
    call with the same text and ``weights`` (the tensors ``compute`` projects with, at the same
    versions; None entries, absent biases, are skipped). Nothing is kept unless ``keep``, with
    gradients enabled or during a CUDA-graph capture."""
    if not keep or torch.is_grad_enabled() or capturing(text):
        return compute()
    weights = [w for w in weights if w is not None]
    check = (text._version,) + tuple(w._version for w in weights)
    memo = text.__dict__.setdefault(_MEMO, {})
    entry = memo.get(id(layer))
    if (entry is not None and entry[0] is layer and entry[1] == check and len(entry[2]) == len(weights)
            and all(a is b for a, b in zip(entry[2], weights))):
        return entry[3]
    kv = compute()
    memo[id(layer)] = (layer, check, tuple(weights), kv)
    return kv


def branch_text(owner: object, embeddings: torch.Tensor, counts: Sequence[int]) -> torch.Tensor:
    """[Σcounts, T, D] text rows of a guidance's branches: row i of ``embeddings`` [R, T, D]
    repeated ``counts[i]`` times, as one tensor kept on ``owner`` per ``counts`` (and rebuilt when
    ``embeddings`` is another tensor or changed in place), so that the cross-attentions' memo on it
    (:func:`memo_text_kv`) is found on the next call. During a CUDA-graph capture a missing entry
    is built but not kept."""
    if len(counts) != embeddings.shape[0]:
        raise ValueError(f"tiger.edit: branch_text needs one count per text row, got {len(counts)} for "
                         f"{embeddings.shape[0]} rows")
    key = tuple(int(c) for c in counts)
    rows = owner.__dict__.setdefault(_ROWS, {})
    entry = rows.get(key)
    if entry is not None and entry[0] is embeddings and entry[1] == embeddings._version:
        return entry[2]
    built = torch.cat([embeddings[i:i + 1].expand(c, -1, -1) for i, c in enumerate(key)])
    if not capturing(embeddings) and not built.requires_grad:
        rows[key] = (embeddings, embeddings._version, built)
    return built
