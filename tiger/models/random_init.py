"""Randomly initialised CLIP and SAM of the real architectures, saved in the public formats.

Tests use the ``tiny`` sizes (hidden 32, 2 layers, 64-pixel inputs) and load them back through
the real loaders; benchmarks use ``full`` (CLIP ViT-B/16, SAM ViT-H: the cost of the real
weights). Nothing here downloads anything.
"""
from __future__ import annotations

import json
from pathlib import Path

import torch

from tiger.utils.lazy import require

from .paths import PathLike


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
    transformers = require("transformers", purpose="building CLIP configs")
    if size == "full":  # openai/clip-vit-base-patch16
        text = dict(vocab_size=49408, hidden_size=512, intermediate_size=2048, num_hidden_layers=12,
                    num_attention_heads=8, max_position_embeddings=77)
        vision = dict(hidden_size=768, intermediate_size=3072, num_hidden_layers=12, num_attention_heads=12,
                      image_size=224, patch_size=16)
        proj = 512
    elif size == "tiny":
        v = vocab_size or 1024
        text = dict(vocab_size=v, bos_token_id=v - 2, eos_token_id=v - 1, pad_token_id=v - 1, hidden_size=32, intermediate_size=64, num_hidden_layers=2,
                    num_attention_heads=2, max_position_embeddings=77)
        vision = dict(hidden_size=32, intermediate_size=64, num_hidden_layers=2, num_attention_heads=2,
                      image_size=64, patch_size=16)
        proj = 24
    else:
        raise ValueError(f"tiger: size must be 'tiny' or 'full', got {size!r}")
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
    transformers = require("transformers", purpose="building SAM configs")
    if size == "full":  # facebook/sam-vit-huge
        vision = dict(hidden_size=1280, num_hidden_layers=32, num_attention_heads=16,
                      global_attn_indexes=[7, 15, 23, 31])
        return transformers.SamConfig(vision_config=vision)
    if size != "tiny":
        raise ValueError(f"tiger: size must be 'tiny' or 'full', got {size!r}")
    vision = dict(hidden_size=32, num_hidden_layers=2, num_attention_heads=2, image_size=64, patch_size=16,
                  mlp_dim=64, output_channels=32, window_size=2, global_attn_indexes=[1], num_pos_feats=16)
    prompt = dict(hidden_size=32, image_size=64, patch_size=16, mask_input_channels=4)
    decoder = dict(hidden_size=32, mlp_dim=64, num_hidden_layers=2, num_attention_heads=4, iou_head_hidden_dim=32)
    return transformers.SamConfig(vision_config=vision, prompt_encoder_config=prompt, mask_decoder_config=decoder)


def random_sam(size: str = "tiny", seed: int = 0):
    transformers = require("transformers", purpose="building a random SAM")
    torch.manual_seed(seed)
    return transformers.SamModel(sam_config(size)).eval()


def save_random_sam(folder: PathLike, size: str = "tiny", seed: int = 0) -> Path:
    """A random SAM as a ``save_pretrained`` folder."""
    folder = Path(folder)
    random_sam(size, seed).save_pretrained(str(folder))
    return folder
