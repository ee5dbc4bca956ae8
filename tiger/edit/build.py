"""Build a guidance by name for the CLI and the notebooks: ``recolor``, ``ip2p``, ``mvdream``, ``ip2p+mvdream``."""
from __future__ import annotations

from pathlib import Path
from typing import Optional, Union

import torch

from .csd import CSDGuidance, CSDSchedule
from .guidance.base import Guidance
from .guidance.recolor import RecolorGuidance

KINDS = ("recolor", "ip2p", "mvdream", "ip2p+mvdream")


def build_guidance(kind: str, instruction: str, *, models: Optional[str] = None,
                   device: Union[str, torch.device] = "cpu", color: Optional[str] = None, seed: int = 0,
                   schedule: CSDSchedule = CSDSchedule(), dtype: Optional[torch.dtype] = None,
                   cuda_graph: Optional[bool] = None, ip2p_kwargs: Optional[dict] = None,
                   mvdream_kwargs: Optional[dict] = None) -> Guidance:
    """The guidance ``kind`` for ``instruction``.

    ``instruction`` is given here only: the guidance carries it (``guidance.instruction``) and
    :func:`tiger.edit.edit` records it from there. ``schedule`` is the CSD λ schedule of
    ``ip2p+mvdream`` (recorded by ``guidance.settings()``).
    ``recolor`` takes its colour from ``color`` or from a colour word in the instruction. The
    diffusion guidances load their weights from ``models`` / ``$TIGER_MODELS`` (an error names the
    files and the public id when they are missing); ``ip2p+mvdream`` is their CSD combination.
    Their noise comes from generators seeded with ``seed`` and ``seed + 1`` (checkpointed by the
    edit loop). ``dtype`` is the models' and ``cuda_graph`` replays each guidance step as a CUDA
    graph; None picks by device (:func:`default_model_dtype`; graphs on CUDA), the settings the
    GPU benchmarks measure. The ``*_kwargs`` go to the guidance constructors (``t_range``, ...).
    """
    ip2p_kwargs, mvdream_kwargs = dict(ip2p_kwargs or {}), dict(mvdream_kwargs or {})
    if kind not in KINDS:
        raise ValueError(f"tiger.edit: guidance must be one of {KINDS}, got {kind!r}")
    if kind == "recolor":
        return RecolorGuidance(instruction, color=color)
    dev = torch.device(device)
    dtype = default_model_dtype(dev) if dtype is None else dtype
    graphs = dev.type == "cuda" if cuda_graph is None else bool(cuda_graph)
    ip2p_kwargs.setdefault("cuda_graph", graphs)
    mvdream_kwargs.setdefault("cuda_graph", graphs)
    models = _model_config(models)
    ip2p = mv = None
    if "ip2p" in kind:
        from .guidance.ip2p import InstructPix2PixGuidance

        ip2p = InstructPix2PixGuidance.from_registry(instruction, config=models, device=device, dtype=dtype,
                                                     generator=torch.Generator().manual_seed(seed), **ip2p_kwargs)
    if "mvdream" in kind:
        from .guidance.mvdream import MVDreamGuidance

        mv = MVDreamGuidance.from_registry(instruction, config=models, device=device, dtype=dtype,
                                           generator=torch.Generator().manual_seed(seed + 1), **mvdream_kwargs)
    return CSDGuidance(ip2p, mv, schedule)


def default_model_dtype(device: Union[str, torch.device]) -> torch.dtype:
    """The diffusion models' dtype when none is given: bfloat16 on a GPU that has it (fp16's range
    without its overflow; half of float32's memory and its tensor-core speed), float16 on older
    GPUs, float32 on the CPU (whose half-precision matmuls are slow)."""
    dev = torch.device(device)
    if dev.type != "cuda":
        return torch.float32
    return torch.bfloat16 if torch.cuda.is_bf16_supported() else torch.float16


def _model_config(models: Optional[str]) -> Union[None, str, dict]:
    """``--models``: a JSON config {name: path} as is; a folder is read like ``$TIGER_MODELS``
    (``instruct-pix2pix/``, ``mvdream/`` or ``sd-v2.1-base-4view.pt`` inside it)."""
    if models is None:
        return None
    root = Path(models).expanduser()
    if root.suffix == ".json" or root.is_file():
        return str(root)
    from tiger.models.paths import REGISTRY

    mv = root / "sd-v2.1-base-4view.pt"
    return {"ip2p": str(root / REGISTRY["ip2p"].folder),
            "mvdream": str(mv if mv.is_file() else root / REGISTRY["mvdream"].folder)}


__all__ = ["KINDS", "build_guidance", "default_model_dtype"]
