"""Original (LDM-layout) Stable Diffusion / MVDream checkpoints → diffusers and transformers state dicts.

diffusers converts LDM checkpoints in ``diffusers.loaders.single_file_utils``, which is not a
public API: this module is the one place that calls it, and ``tests/edit/test_ldm_checkpoint.py``
pins the mapping (an LDM checkpoint written by an independent inverse converts back bit-exactly).

A flat LDM state dict holds ``model.diffusion_model.*`` (UNet), ``first_stage_model.*`` (VAE) and
``cond_stage_model.model.*`` (the OpenCLIP text tower, used at its penultimate layer: the last
residual block is dropped and ``ln_final`` applied, as SD-2's diffusers text encoder does).
MVDream adds ``model.diffusion_model.camera_embed.{0,2}.*`` (Linear(16,1280)–SiLU–Linear(1280,1280)
added to the timestep embedding), which is diffusers' ``class_embed_type="projection"``.
"""
from __future__ import annotations

import copy
import importlib
import json
import re
import warnings
from dataclasses import dataclass
from pathlib import Path
from types import SimpleNamespace
from typing import Mapping, Union

import torch

from tiger.utils.lazy import require_diffusers

from .noise_schedule import NoiseSchedule

UNET_PREFIX = "model.diffusion_model."
TEXT_PREFIX = "cond_stage_model.model."
OPENCLIP_HEAD_WIDTH = 64  # open_clip text towers: heads = width // 64 (ViT-H-14: 1024 / 64 = 16)

# MVDream's mvdream/configs/sd-v2-base.yaml (the fields the conversion reads).
MVDREAM_SD21_LDM_CONFIG: dict = {
    "model": {
        "params": {
            "linear_start": 0.00085,
            "linear_end": 0.012,
            "timesteps": 1000,
            "scale_factor": 0.18215,
            "parameterization": "eps",
            "unet_config": {
                "params": {
                    "image_size": 32,
                    "in_channels": 4,
                    "out_channels": 4,
                    "model_channels": 320,
                    "attention_resolutions": [4, 2, 1],
                    "num_res_blocks": 2,
                    "channel_mult": [1, 2, 4, 4],
                    "num_head_channels": 64,
                    "use_spatial_transformer": True,
                    "use_linear_in_transformer": True,
                    "transformer_depth": 1,
                    "context_dim": 1024,
                    "camera_dim": 16,
                }
            },
            "first_stage_config": {
                "params": {
                    "embed_dim": 4,
                    "ddconfig": {
                        "double_z": True, "z_channels": 4, "resolution": 256, "in_channels": 3, "out_ch": 3,
                        "ch": 128, "ch_mult": [1, 2, 4, 4], "num_res_blocks": 2, "attn_resolutions": [],
                    },
                }
            },
        }
    }
}

StateDict = dict[str, torch.Tensor]
ConfigSource = Union[None, str, Path, Mapping]


@dataclass
class LDMComponents:
    """A converted LDM checkpoint: diffusers UNet/VAE configs and state dicts, the transformers
    ``CLIPTextConfig`` kwargs and state dict (keys without the ``text_model.`` prefix), the schedule."""

    unet_config: dict
    unet_state: StateDict
    vae_config: dict
    vae_state: StateDict
    text_config: dict
    text_state: StateDict
    schedule: NoiseSchedule


def _single_file_utils():
    """diffusers' (non-public) LDM converters: the one import of them in the package."""
    require_diffusers("converting LDM checkpoints")
    return importlib.import_module("diffusers.loaders.single_file_utils")


def read_ldm_config(source: ConfigSource) -> dict:
    """An LDM config (the ``model: params:`` tree) from a mapping, a .json or a .yaml file; None: MVDream's."""
    if source is None:
        return copy.deepcopy(MVDREAM_SD21_LDM_CONFIG)
    if isinstance(source, Mapping):
        return copy.deepcopy(dict(source))
    path = Path(source)
    try:
        text = path.read_text()
    except OSError as exc:
        raise ValueError(f"tiger.edit: cannot read the LDM config {path}: {exc}") from exc
    if path.suffix in (".yaml", ".yml"):
        from tiger.utils.lazy import require

        cfg = require("yaml", pip_name="pyyaml", purpose=f"reading {path}").safe_load(text)
    else:
        cfg = json.loads(text)
    if not isinstance(cfg, dict) or "unet_config" not in cfg.get("model", {}).get("params", {}):
        raise ValueError(f"tiger.edit: {path} is not an LDM config (expected model.params.unet_config)")
    return cfg


def _unet_params(ldm_config: dict) -> dict:
    return ldm_config["model"]["params"]["unet_config"]["params"]


def _vae_scale(ldm_config: dict) -> int:
    ddconfig = ldm_config["model"]["params"]["first_stage_config"]["params"]["ddconfig"]
    return 2 ** (len(ddconfig["ch_mult"]) - 1)


def unet_config_from_ldm(ldm_config: ConfigSource = None) -> dict:
    """diffusers ``UNet2DConditionModel`` kwargs; a ``camera_dim`` becomes the projection class embedding."""
    su = _single_file_utils()
    ldm_config = read_ldm_config(ldm_config)
    params = _unet_params(ldm_config)
    image_size = int(params.get("image_size", 32)) * _vae_scale(ldm_config)
    with warnings.catch_warnings():  # image_size is passed so that nothing is inferred from key names
        warnings.simplefilter("ignore")
        cfg = su.create_unet_diffusers_config_from_ldm(ldm_config, {}, image_size=image_size)
    if params.get("camera_dim"):
        cfg["class_embed_type"] = "projection"
        cfg["projection_class_embeddings_input_dim"] = int(params["camera_dim"])
    return cfg


def vae_config_from_ldm(ldm_config: ConfigSource = None) -> dict:
    """diffusers ``AutoencoderKL`` kwargs (scaling factor from ``scale_factor``)."""
    su = _single_file_utils()
    ldm_config = read_ldm_config(ldm_config)
    ddconfig = ldm_config["model"]["params"]["first_stage_config"]["params"]["ddconfig"]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return su.create_vae_diffusers_config_from_ldm(ldm_config, {}, image_size=int(ddconfig["resolution"]))


def openclip_text_config(state: Mapping[str, torch.Tensor], prefix: str = TEXT_PREFIX) -> dict:
    """``CLIPTextConfig`` kwargs of an OpenCLIP text tower used at its penultimate layer."""
    blocks = {int(m.group(1)) for k in state if (m := re.match(re.escape(prefix) + r"transformer\.resblocks\.(\d+)\.", k))}
    if not blocks:
        raise ValueError(f"tiger.edit: the checkpoint has no text tower ({prefix}transformer.resblocks.*)")
    if blocks != set(range(len(blocks))) or len(blocks) < 2:
        raise ValueError(f"tiger.edit: text tower blocks must be 0..L-1 with L >= 2, found {sorted(blocks)}")
    vocab, width = state[prefix + "token_embedding.weight"].shape
    heads = max(1, width // OPENCLIP_HEAD_WIDTH)
    return dict(
        vocab_size=int(vocab), hidden_size=int(width), num_attention_heads=int(heads),
        intermediate_size=int(state[prefix + "transformer.resblocks.0.mlp.c_fc.weight"].shape[0]),
        num_hidden_layers=len(blocks) - 1, max_position_embeddings=int(state[prefix + "positional_embedding"].shape[0]),
        hidden_act="gelu", layer_norm_eps=1e-5, projection_dim=int(width),
        bos_token_id=min(49406, int(vocab) - 2), eos_token_id=min(49407, int(vocab) - 1), pad_token_id=0,
    )


def convert_ldm_checkpoint(checkpoint: Mapping[str, torch.Tensor], ldm_config: ConfigSource = None) -> LDMComponents:
    """Split and convert a flat LDM (MVDream) state dict. ``ldm_config``: see :func:`read_ldm_config`."""
    su = _single_file_utils()
    cfg = read_ldm_config(ldm_config)
    state = dict(checkpoint.get("state_dict", checkpoint)) if isinstance(checkpoint.get("state_dict"), Mapping) else dict(checkpoint)
    if not any(k.startswith(UNET_PREFIX) for k in state):
        raise ValueError(f"tiger.edit: not an LDM checkpoint (no '{UNET_PREFIX}*' keys)")
    for i in (0, 2):  # MVDream's camera MLP is diffusers' projection class embedding (LDM label_emb.0)
        for p in ("weight", "bias"):
            old = f"{UNET_PREFIX}camera_embed.{i}.{p}"
            if old in state:
                state[f"{UNET_PREFIX}label_emb.0.{i}.{p}"] = state.pop(old)
    unet_config = unet_config_from_ldm(cfg)
    if unet_config.get("class_embed_type") == "projection" and f"{UNET_PREFIX}label_emb.0.0.weight" not in state:
        raise ValueError("tiger.edit: the config has camera_dim but the checkpoint has no camera_embed.* weights")
    vae_config = vae_config_from_ldm(cfg)
    text_config = openclip_text_config(state)
    last = text_config["num_hidden_layers"]  # penultimate layer: drop the last block
    text_in = {k: v for k, v in state.items()
               if k.startswith(TEXT_PREFIX) and not k.startswith(f"{TEXT_PREFIX}transformer.resblocks.{last}.")}
    text_model = SimpleNamespace(config=SimpleNamespace(hidden_size=text_config["hidden_size"]))
    text_state = su.convert_open_clip_checkpoint(text_model, text_in, prefix=TEXT_PREFIX)
    text_state = {k.removeprefix("text_model."): v for k, v in text_state.items() if k != "text_projection.weight"}
    params = cfg["model"]["params"]
    schedule = NoiseSchedule.from_betas(float(params.get("linear_start", 0.00085)), float(params.get("linear_end", 0.012)),
                                        int(params.get("timesteps", 1000)), "scaled_linear")
    stored = state.get("alphas_cumprod")  # LDM checkpoints carry their schedule: it must agree with the config
    if stored is not None and (stored.shape != schedule.alphas_cumprod.shape
                               or not torch.allclose(stored.float(), schedule.alphas_cumprod, atol=1e-6)):
        raise ValueError("tiger.edit: the checkpoint's alphas_cumprod disagrees with the config's "
                         "linear_start/linear_end/timesteps")
    return LDMComponents(
        unet_config=unet_config, unet_state=su.convert_ldm_unet_checkpoint(state, unet_config),
        vae_config=vae_config, vae_state=su.convert_ldm_vae_checkpoint(state, vae_config),
        text_config=text_config, text_state=text_state, schedule=schedule,
    )
