"""Randomly initialised models of the real architectures, saved in the public formats.

CLIP and SAM are ``save_pretrained`` folders (CLIP with a small byte-level BPE tokenizer);
InstructPix2Pix is a diffusers folder; MVDream is its flat LDM ``.pt``, written by an inverse of the
key mapping that is independent of diffusers' converter. ``tiny`` sizes (hidden widths of 32-64,
1-2 layers) are for tests and load back through the real loaders; ``full`` sizes (CLIP ViT-B/16,
SAM ViT-H, SD-1.5 InstructPix2Pix, SD-2.1-base MVDream) are for benchmarks and examples: the cost of
the real weights without downloading them. Nothing here downloads anything.
"""
from __future__ import annotations

import copy
import json
import re
from pathlib import Path

import torch

from tiger.edit.guidance.ldm_checkpoint import (MVDREAM_SD21_LDM_CONFIG, TEXT_PREFIX, UNET_PREFIX,
                                                unet_config_from_ldm, vae_config_from_ldm)
from tiger.utils.lazy import require, require_diffusers
from tiger.models.paths import PathLike

CHECKPOINT_NAME = "sd-v2.1-base-4view.pt"
TINY_LDM_CONFIG_NAME = "sd-v2-base.json"


def _check_size(size: str) -> None:
    if size not in ("tiny", "full"):
        raise ValueError(f"tiger: size must be 'tiny' or 'full', got {size!r}")


def _bytes_to_unicode() -> dict[int, str]:
    # GPT-2/CLIP byte-level alphabet: printable bytes map to themselves, the rest above 255.
    bs = list(range(ord("!"), ord("~") + 1)) + list(range(ord("¡"), ord("¬") + 1)) + list(range(ord("®"), ord("ÿ") + 1))
    cs = bs[:]
    n = 0
    for b in range(256):
        if b not in bs:
            bs.append(b)
            cs.append(256 + n)
            n += 1
    return dict(zip(bs, (chr(c) for c in cs)))


def write_byte_level_clip_tokenizer(folder: PathLike, merges: tuple[str, ...] = ("t h", "th e</w>", "a </w>")) -> int:
    """A small CLIP BPE tokenizer (every byte, with and without ``</w>``, a few merges, the two
    special tokens) as ``vocab.json`` + ``merges.txt``; returns the vocabulary size."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    alphabet = list(_bytes_to_unicode().values())
    tokens = alphabet + [a + "</w>" for a in alphabet]
    for m in merges:
        tokens.append(m.replace(" ", ""))
    tokens += ["</w>", "<|startoftext|>", "<|endoftext|>"]
    vocab = {t: i for i, t in enumerate(dict.fromkeys(tokens))}
    (folder / "vocab.json").write_text(json.dumps(vocab, ensure_ascii=False))
    (folder / "merges.txt").write_text("#version: 0.2\n" + "\n".join(merges) + "\n", encoding="utf-8")
    return len(vocab)


def clip_config(size: str = "tiny", vocab_size: int | None = None):
    """``CLIPConfig`` of CLIP ViT-B/16 (``full``) or a 2-layer, 32-wide CLIP (``tiny``, ``vocab_size`` tokens)."""
    _check_size(size)
    transformers = require("transformers", purpose="building CLIP configs")
    if size == "full":  # openai/clip-vit-base-patch16
        text = dict(vocab_size=49408, hidden_size=512, intermediate_size=2048, num_hidden_layers=12,
                    num_attention_heads=8, max_position_embeddings=77)
        vision = dict(hidden_size=768, intermediate_size=3072, num_hidden_layers=12, num_attention_heads=12,
                      image_size=224, patch_size=16)
        proj = 512
    else:
        v = vocab_size or 1024
        text = dict(vocab_size=v, bos_token_id=v - 2, eos_token_id=v - 1, pad_token_id=v - 1, hidden_size=32, intermediate_size=64, num_hidden_layers=2,
                    num_attention_heads=2, max_position_embeddings=77)
        vision = dict(hidden_size=32, intermediate_size=64, num_hidden_layers=2, num_attention_heads=2,
                      image_size=64, patch_size=16)
        proj = 24
    return transformers.CLIPConfig(text_config=text, vision_config=vision, projection_dim=proj)


def save_random_clip(folder: PathLike, size: str = "tiny", seed: int = 0) -> Path:
    """A random CLIP (``save_pretrained`` folder with a byte-level tokenizer)."""
    transformers = require("transformers", purpose="building a random CLIP")
    folder = Path(folder)
    torch.manual_seed(seed)
    vocab = write_byte_level_clip_tokenizer(folder)
    cfg = clip_config(size, vocab)
    if size == "full":  # the small tokenizer's end token is the id CLIP pools at
        cfg.text_config.eos_token_id = vocab - 1
    transformers.CLIPModel(cfg).save_pretrained(str(folder))
    return folder


def sam_config(size: str = "tiny"):
    """``SamConfig`` of SAM ViT-H (``full``) or a 2-layer, 32-wide SAM on 64-pixel inputs (``tiny``)."""
    _check_size(size)
    transformers = require("transformers", purpose="building SAM configs")
    if size == "full":  # facebook/sam-vit-huge
        vision = dict(hidden_size=1280, num_hidden_layers=32, num_attention_heads=16,
                      global_attn_indexes=[7, 15, 23, 31])
        return transformers.SamConfig(vision_config=vision)
    vision = dict(hidden_size=32, num_hidden_layers=2, num_attention_heads=2, image_size=64, patch_size=16,
                  mlp_dim=64, output_channels=32, window_size=2, global_attn_indexes=[1], num_pos_feats=16)
    prompt = dict(hidden_size=32, image_size=64, patch_size=16, mask_input_channels=4)
    decoder = dict(hidden_size=32, mlp_dim=64, num_hidden_layers=2, num_attention_heads=4, iou_head_hidden_dim=32)
    return transformers.SamConfig(vision_config=vision, prompt_encoder_config=prompt, mask_decoder_config=decoder)


def random_sam(size: str = "tiny", seed: int = 0):
    """A randomly initialised ``SamModel`` in eval mode, seeded by ``seed``."""
    transformers = require("transformers", purpose="building a random SAM")
    torch.manual_seed(seed)
    return transformers.SamModel(sam_config(size)).eval()


def save_random_sam(folder: PathLike, size: str = "tiny", seed: int = 0) -> Path:
    """A random SAM as a ``save_pretrained`` folder."""
    folder = Path(folder)
    random_sam(size, seed).save_pretrained(str(folder))
    return folder


def ip2p_unet_config(size: str = "tiny") -> dict:
    """SD-1.5 UNet with 8 input channels (InstructPix2Pix), or a tiny one of the same block types."""
    _check_size(size)
    if size == "full":
        return dict(sample_size=64, in_channels=8, out_channels=4, layers_per_block=2,
                    block_out_channels=(320, 640, 1280, 1280), cross_attention_dim=768, attention_head_dim=8,
                    down_block_types=("CrossAttnDownBlock2D",) * 3 + ("DownBlock2D",),
                    up_block_types=("UpBlock2D",) + ("CrossAttnUpBlock2D",) * 3)
    return dict(sample_size=8, in_channels=8, out_channels=4, layers_per_block=1, block_out_channels=(32, 64),
                cross_attention_dim=32, attention_head_dim=8, norm_num_groups=8,
                down_block_types=("CrossAttnDownBlock2D", "DownBlock2D"), up_block_types=("UpBlock2D", "CrossAttnUpBlock2D"))


def sd_vae_config(size: str = "tiny") -> dict:
    """The SD VAE (4 latent channels, factor 8), or a tiny one (factor 2)."""
    _check_size(size)
    blocks = (128, 256, 512, 512) if size == "full" else (32, 64)
    return dict(in_channels=3, out_channels=3, latent_channels=4, block_out_channels=blocks,
                layers_per_block=2 if size == "full" else 1, sample_size=512 if size == "full" else 32,
                down_block_types=("DownEncoderBlock2D",) * len(blocks), up_block_types=("UpDecoderBlock2D",) * len(blocks),
                scaling_factor=0.18215)


def _write_tokenizer(folder: Path, pad_token: str) -> int:
    transformers = require("transformers", purpose="writing a CLIP tokenizer")
    vocab = write_byte_level_clip_tokenizer(folder)
    tok = transformers.CLIPTokenizer(str(folder / "vocab.json"), str(folder / "merges.txt"), pad_token=pad_token,
                                     model_max_length=77)
    tok.save_pretrained(str(folder))
    return vocab


def save_random_ip2p(folder: PathLike, size: str = "tiny", seed: int = 0) -> Path:
    """A random InstructPix2Pix as a diffusers folder (unet/, vae/, text_encoder/, tokenizer/, scheduler/)."""
    diffusers = require_diffusers("building a random InstructPix2Pix")
    transformers = require("transformers", purpose="building a random InstructPix2Pix")
    folder = Path(folder)
    torch.manual_seed(seed)
    vocab = _write_tokenizer(folder / "tokenizer", "<|endoftext|>")
    diffusers.UNet2DConditionModel(**ip2p_unet_config(size)).save_pretrained(str(folder / "unet"))
    diffusers.AutoencoderKL(**sd_vae_config(size)).save_pretrained(str(folder / "vae"))
    if size == "full":  # CLIP ViT-L/14 text tower
        text = dict(vocab_size=49408, hidden_size=768, intermediate_size=3072, num_hidden_layers=12, num_attention_heads=12)
    else:
        text = dict(vocab_size=vocab, hidden_size=32, intermediate_size=64, num_hidden_layers=2, num_attention_heads=2)
    text.update(max_position_embeddings=77, bos_token_id=min(49406, vocab - 2), eos_token_id=min(49407, vocab - 1),
                pad_token_id=min(49407, vocab - 1))
    if size == "full":
        text.update(bos_token_id=vocab - 2, eos_token_id=vocab - 1, pad_token_id=vocab - 1)
    transformers.CLIPTextModel(transformers.CLIPTextConfig(**text)).save_pretrained(str(folder / "text_encoder"))
    sched = {"_class_name": "EulerAncestralDiscreteScheduler", "beta_start": 0.00085, "beta_end": 0.012,
             "beta_schedule": "scaled_linear", "num_train_timesteps": 1000, "prediction_type": "epsilon",
             "steps_offset": 1}
    (folder / "scheduler").mkdir(parents=True, exist_ok=True)
    (folder / "scheduler" / "scheduler_config.json").write_text(json.dumps(sched, indent=2))
    (folder / "model_index.json").write_text(json.dumps({"_class_name": "StableDiffusionInstructPix2PixPipeline"}))
    return folder


def mvdream_ldm_config(size: str = "tiny") -> dict:
    """MVDream's sd-v2-base LDM config, or a tiny one of the same structure."""
    _check_size(size)
    cfg = copy.deepcopy(MVDREAM_SD21_LDM_CONFIG)
    if size == "tiny":
        p = cfg["model"]["params"]
        p["unet_config"]["params"].update(image_size=8, model_channels=32, attention_resolutions=[1], num_res_blocks=1,
                                          channel_mult=[1, 2], num_head_channels=16, context_dim=64)
        p["first_stage_config"]["params"]["ddconfig"].update(resolution=32, ch=32, ch_mult=[1, 2], num_res_blocks=1)
    return cfg


# -- the inverse of the LDM -> diffusers key mapping (written from the LDM module layout) ------------
_RESNET = [("norm1", "in_layers.0"), ("conv1", "in_layers.2"), ("time_emb_proj", "emb_layers.1"),
           ("norm2", "out_layers.0"), ("conv2", "out_layers.3"), ("conv_shortcut", "skip_connection")]


def _resnet_to_ldm(rest: str) -> str:
    for new, old in _RESNET:
        if rest.startswith(new + "."):
            return old + rest[len(new):]
    raise KeyError(rest)


def unet_to_ldm(state: dict[str, torch.Tensor], config: dict) -> dict[str, torch.Tensor]:
    """diffusers UNet2DConditionModel keys -> LDM ``model.diffusion_model.*`` (MVDream's camera_embed)."""
    per = config["layers_per_block"] + 1
    has_attn = ["CrossAttn" in t for t in config["up_block_types"]]
    fixed = {"time_embedding.linear_1": "time_embed.0", "time_embedding.linear_2": "time_embed.2",
             "class_embedding.linear_1": "camera_embed.0", "class_embedding.linear_2": "camera_embed.2",
             "conv_in": "input_blocks.0.0", "conv_norm_out": "out.0", "conv_out": "out.2"}
    out = {}
    for key, value in state.items():
        head, _, param = key.rpartition(".")
        if head in fixed:
            new = f"{fixed[head]}.{param}"
        elif m := re.fullmatch(r"down_blocks\.(\d+)\.resnets\.(\d+)\.(.+)", key):
            b, j, rest = int(m[1]), int(m[2]), m[3]
            new = f"input_blocks.{1 + b * per + j}.0.{_resnet_to_ldm(rest)}"
        elif m := re.fullmatch(r"down_blocks\.(\d+)\.attentions\.(\d+)\.(.+)", key):
            new = f"input_blocks.{1 + int(m[1]) * per + int(m[2])}.1.{m[3]}"
        elif m := re.fullmatch(r"down_blocks\.(\d+)\.downsamplers\.0\.conv\.(.+)", key):
            new = f"input_blocks.{(int(m[1]) + 1) * per}.0.op.{m[2]}"
        elif m := re.fullmatch(r"mid_block\.resnets\.(\d+)\.(.+)", key):
            new = f"middle_block.{2 * int(m[1])}.{_resnet_to_ldm(m[2])}"
        elif m := re.fullmatch(r"mid_block\.attentions\.0\.(.+)", key):
            new = f"middle_block.1.{m[1]}"
        elif m := re.fullmatch(r"up_blocks\.(\d+)\.resnets\.(\d+)\.(.+)", key):
            new = f"output_blocks.{int(m[1]) * per + int(m[2])}.0.{_resnet_to_ldm(m[3])}"
        elif m := re.fullmatch(r"up_blocks\.(\d+)\.attentions\.(\d+)\.(.+)", key):
            new = f"output_blocks.{int(m[1]) * per + int(m[2])}.1.{m[3]}"
        elif m := re.fullmatch(r"up_blocks\.(\d+)\.upsamplers\.0\.conv\.(.+)", key):
            b = int(m[1])
            new = f"output_blocks.{b * per + per - 1}.{2 if has_attn[b] else 1}.conv.{m[2]}"
        else:
            raise KeyError(f"unmapped UNet key {key}")
        out[UNET_PREFIX + new] = value
    return out


def vae_to_ldm(state: dict[str, torch.Tensor], config: dict) -> dict[str, torch.Tensor]:
    """diffusers AutoencoderKL keys -> LDM ``first_stage_model.*`` (attention projections as 1x1 convs)."""
    n = len(config["block_out_channels"])
    attn = {"group_norm": "norm", "to_q": "q", "to_k": "k", "to_v": "v", "to_out.0": "proj_out"}
    out = {}
    for key, value in state.items():
        new = key.replace("conv_norm_out", "norm_out")
        if m := re.fullmatch(r"(encoder|decoder)\.(down|up)_blocks\.(\d+)\.(resnets|downsamplers|upsamplers)\.(\d+)\.(.+)", key):
            part, kind, i, sub, j, rest = m.groups()
            level = int(i) if kind == "down" else n - 1 - int(i)
            rest = rest.replace("conv_shortcut", "nin_shortcut")
            new = (f"{part}.{kind}.{level}.block.{j}.{rest}" if sub == "resnets"
                   else f"{part}.{kind}.{level}.{'downsample' if kind == 'down' else 'upsample'}.{rest}")
        elif m := re.fullmatch(r"(encoder|decoder)\.mid_block\.resnets\.(\d+)\.(.+)", key):
            new = f"{m[1]}.mid.block_{int(m[2]) + 1}.{m[3].replace('conv_shortcut', 'nin_shortcut')}"
        elif m := re.fullmatch(r"(encoder|decoder)\.mid_block\.attentions\.0\.(.+)\.(weight|bias)", key):
            new = f"{m[1]}.mid.attn_1.{attn[m[2]]}.{m[3]}"
            if m[3] == "weight" and m[2] != "group_norm":
                value = value[:, :, None, None]
        out["first_stage_model." + new] = value
    return out


def text_to_openclip(state: dict[str, torch.Tensor], extra_block: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    """transformers CLIPTextModel keys -> OpenCLIP ``cond_stage_model.model.*``; ``extra_block`` is the
    last residual block (unused at the penultimate layer) in OpenCLIP names, appended."""
    names = {"layer_norm1": "ln_1", "layer_norm2": "ln_2", "mlp.fc1": "mlp.c_fc", "mlp.fc2": "mlp.c_proj",
             "self_attn.out_proj": "attn.out_proj"}
    out = {}
    qkv: dict[tuple[int, str], dict[str, torch.Tensor]] = {}
    for key, value in state.items():
        key = key.removeprefix("text_model.")
        if key == "embeddings.token_embedding.weight":
            out["token_embedding.weight"] = value
        elif key == "embeddings.position_embedding.weight":
            out["positional_embedding"] = value
        elif key.startswith("final_layer_norm."):
            out["ln_final." + key.split(".")[-1]] = value
        elif m := re.fullmatch(r"encoder\.layers\.(\d+)\.self_attn\.([qkv])_proj\.(weight|bias)", key):
            qkv.setdefault((int(m[1]), m[3]), {})[m[2]] = value
        elif m := re.fullmatch(r"encoder\.layers\.(\d+)\.(.+)\.(weight|bias)", key):
            out[f"transformer.resblocks.{m[1]}.{names[m[2]]}.{m[3]}"] = value
        elif key != "embeddings.position_ids":
            raise KeyError(f"unmapped text key {key}")
    for (i, p), parts in qkv.items():
        out[f"transformer.resblocks.{i}.attn.in_proj_{p}"] = torch.cat([parts["q"], parts["k"], parts["v"]])
    out.update(extra_block)
    return {TEXT_PREFIX + k: v for k, v in out.items()}


def random_mvdream_state(size: str = "tiny", seed: int = 0, vocab_size: int = 49408
                         ) -> tuple[dict[str, torch.Tensor], dict[str, dict[str, torch.Tensor]]]:
    """A random MVDream as a flat LDM state dict, and the diffusers/transformers state dicts it was
    made from (``{"unet", "vae", "text"}``): UNet with camera_embed, VAE, an OpenCLIP text tower
    with one block more than used, text_projection, logit_scale and the LDM schedule buffers."""
    diffusers = require_diffusers("building a random MVDream")
    transformers = require("transformers", purpose="building a random MVDream")
    torch.manual_seed(seed)
    cfg = mvdream_ldm_config(size)
    unet_cfg, vae_cfg = unet_config_from_ldm(cfg), vae_config_from_ldm(cfg)
    unet = diffusers.UNet2DConditionModel(**unet_cfg)
    vae = diffusers.AutoencoderKL(**vae_cfg)
    width, layers, mlp = (1024, 24, 4096) if size == "full" else (64, 3, 128)
    text_cfg = dict(vocab_size=vocab_size, hidden_size=width, intermediate_size=mlp, num_hidden_layers=layers - 1,
                    num_attention_heads=max(1, width // 64), max_position_embeddings=77, hidden_act="gelu",
                    bos_token_id=min(49406, vocab_size - 2), eos_token_id=min(49407, vocab_size - 1), pad_token_id=0)
    text = transformers.CLIPTextModel(transformers.CLIPTextConfig(**text_cfg))
    last = f"transformer.resblocks.{layers - 1}."
    extra = {last + "ln_1.weight": torch.ones(width), last + "ln_1.bias": torch.zeros(width),
             last + "attn.in_proj_weight": torch.randn(3 * width, width) * 0.02, last + "attn.in_proj_bias": torch.zeros(3 * width),
             last + "attn.out_proj.weight": torch.randn(width, width) * 0.02, last + "attn.out_proj.bias": torch.zeros(width),
             last + "ln_2.weight": torch.ones(width), last + "ln_2.bias": torch.zeros(width),
             last + "mlp.c_fc.weight": torch.randn(mlp, width) * 0.02, last + "mlp.c_fc.bias": torch.zeros(mlp),
             last + "mlp.c_proj.weight": torch.randn(width, mlp) * 0.02, last + "mlp.c_proj.bias": torch.zeros(width),
             "text_projection": torch.randn(width, width) * 0.02, "logit_scale": torch.tensor(4.6052)}
    p = cfg["model"]["params"]
    betas = torch.linspace(p["linear_start"] ** 0.5, p["linear_end"] ** 0.5, p["timesteps"], dtype=torch.float64) ** 2
    originals = {"unet": unet.state_dict(), "vae": vae.state_dict(), "text": text.state_dict()}
    state = {**unet_to_ldm(originals["unet"], unet_cfg), **vae_to_ldm(originals["vae"], vae_cfg),
             **text_to_openclip(originals["text"], extra),
             "betas": betas.float(), "alphas_cumprod": torch.cumprod(1 - betas, 0).float()}
    return state, originals


def save_random_mvdream(folder: PathLike, size: str = "tiny", seed: int = 0) -> Path:
    """:func:`random_mvdream_state` saved as ``folder/sd-v2.1-base-4view.pt``, with ``tokenizer/`` and,
    for ``tiny``, the LDM config ``sd-v2-base.json`` the loader reads beside the checkpoint."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    vocab = _write_tokenizer(folder / "tokenizer", "!")
    state, _ = random_mvdream_state(size, seed, 49408 if size == "full" else vocab)
    torch.save(state, folder / CHECKPOINT_NAME)
    if size == "tiny":
        (folder / TINY_LDM_CONFIG_NAME).write_text(json.dumps(mvdream_ldm_config(size), indent=2))
    return folder
