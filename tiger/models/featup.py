"""FeatUp's MaskCLIP JBU checkpoint (``maskclip_jbu_stack_cocostuff.ckpt``)."""
from __future__ import annotations

import logging
from typing import Mapping

import torch

from .paths import ConfigLike, PathLike, resolve_model_path

logger = logging.getLogger(__name__)


def load_jbu_checkpoint(path: PathLike | None = None, *, config: ConfigLike = None) -> dict[str, torch.Tensor]:
    """The JBU upsampler's weights from a FeatUp checkpoint, keyed as :class:`tiger.language.featup.JBUStack`.

    Accepts FeatUp's Lightning checkpoint (``state_dict`` with ``upsampler.*`` keys), a torch.hub
    state dict, or a bare JBUStack state dict.
    """
    found = resolve_model_path("featup_jbu", path, config=config)
    raw = torch.load(str(found), map_location="cpu", weights_only=False)
    state = raw.get("state_dict", raw) if isinstance(raw, Mapping) else None
    if not isinstance(state, Mapping):
        raise ValueError(f"tiger: {found} holds no state dict (got {type(raw).__name__})")
    out: dict[str, torch.Tensor] = {}
    for key, value in state.items():
        for prefix in ("upsampler.", "model.upsampler.", ""):
            if key.startswith(prefix) and key[len(prefix):].split(".")[0] in {"up1", "up2", "up3", "up4", "fixup_proj"}:
                out[key[len(prefix):]] = value
                break
    if not out:
        raise ValueError(f"tiger: {found} has no JBU upsampler weights (keys like 'upsampler.up1.range_temp')")
    logger.info("loaded FeatUp JBU weights from %s (%d tensors)", found, len(out))
    return out
