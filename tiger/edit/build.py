"""Build a guidance by name for the CLI and the notebooks: ``recolor``, ``ip2p``, ``mvdream``, ``ip2p+mvdream``."""
from __future__ import annotations

from typing import Optional, Union

import torch

from .csd import CSDGuidance, CSDSchedule
from .guidance.base import Guidance
from .guidance.recolor import RecolorGuidance

KINDS = ("recolor", "ip2p", "mvdream", "ip2p+mvdream")


def build_guidance(kind: str, instruction: str, *, models: Optional[str] = None,
                   device: Union[str, torch.device] = "cpu", color: Optional[str] = None, seed: int = 0,
                   schedule: CSDSchedule = CSDSchedule()) -> Guidance:
    """The guidance ``kind`` for ``instruction``.

    ``recolor`` takes its colour from ``color`` or from a colour word in the instruction. The
    diffusion guidances load their weights from ``models`` / ``$TIGER_MODELS`` (an error names the
    files and the public id when they are missing); ``ip2p+mvdream`` is their CSD combination.
    """
    if kind not in KINDS:
        raise ValueError(f"tiger.edit: guidance must be one of {KINDS}, got {kind!r}")
    if kind == "recolor":
        return RecolorGuidance(color if color is not None else instruction)
    ip2p = mv = None
    if "ip2p" in kind:
        from .guidance.ip2p import InstructPix2PixGuidance

        ip2p = InstructPix2PixGuidance.from_pretrained(instruction, models=models, device=device, seed=seed)
    if "mvdream" in kind:
        from .guidance.mvdream import MVDreamGuidance

        mv = MVDreamGuidance.from_pretrained(instruction, models=models, device=device, seed=seed + 1)
    return CSDGuidance(ip2p, mv, schedule)


__all__ = ["KINDS", "build_guidance"]
