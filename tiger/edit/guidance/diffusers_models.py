"""The diffusers-model plumbing of the diffusion guidances (InstructPix2Pix, MVDream): VAE
encoding of renders and the gradient back through it, resizing to the model's resolution,
freezing (with tiger's fused norms), the VAE attention processor and the cached prompt encoder.

Losses are ``0.5·‖z − target‖² / V`` (summed over latent elements, averaged over the V views),
so ``dL/dz = g / V``; the noise schedule is :mod:`.noise_schedule`.
"""
from __future__ import annotations

import types
from typing import Callable, Optional

import torch
import torch.nn.functional as F

from tiger.ops.softmax import softmax_rows
from tiger.utils.lazy import require_diffusers

from .fused_norms import apply_fused_norms

ROW_SOFTMAX = "_tiger_row_softmax"  # a VAE attention layer's softmax by tiger's row kernel (ModelKernels.row_softmax)


def vae_downsampling_factor(vae) -> int:
    """Pixels per latent pixel: 2^(number of encoder blocks − 1), from the VAE's config."""
    return 2 ** (len(vae.config.block_out_channels) - 1)


def resolution_for(height: int, width: int, short_side: int, multiple: int) -> tuple[int, int]:
    """(RH, RW) with the shorter side ``short_side``, the aspect ratio kept, both multiples of ``multiple``."""
    scale = short_side / min(height, width)
    rh = max(multiple, int(round(height * scale / multiple)) * multiple)
    rw = max(multiple, int(round(width * scale / multiple)) * multiple)
    return rh, rw


def resize(images: torch.Tensor, size: tuple[int, int]) -> torch.Tensor:
    """Bilinear resize of [V, C, H, W] (no-op when the size already matches)."""
    if tuple(images.shape[-2:]) == tuple(size):
        return images
    return F.interpolate(images, size=size, mode="bilinear", align_corners=False)


def is_channels_last(module: torch.nn.Module) -> bool:
    """True when the module's first conv weight ([out, in, kh, kw], not 1x1 with one input channel,
    where both layouts coincide) is in channels-last memory (see :mod:`.fused_norms`)."""
    for p in module.parameters():
        if p.dim() == 4 and p.shape[1] * p.shape[2] * p.shape[3] > 1:
            return not p.is_contiguous() and p.is_contiguous(memory_format=torch.channels_last)
    return False


def encode_latents(vae, images01: torch.Tensor, vae_noise: Optional[torch.Tensor]) -> torch.Tensor:
    """VAE latents of images in [0, 1] ([V, 3, H, W] -> [V, c, H/f, W/f]).

    ``vae_noise`` given: a posterior sample ``(μ + σ·vae_noise)·scaling_factor`` (the SDS latents);
    None: the posterior mode ``μ``, NOT scaled (InstructPix2Pix's image condition). The 3-channel
    input is made channels-last when the VAE is (one cheap copy instead of cuDNN converting it).
    """
    dtype = next(vae.parameters()).dtype
    images = images01.to(dtype) * 2.0 - 1.0
    if is_channels_last(vae):
        images = images.contiguous(memory_format=torch.channels_last)
    dist = vae.encode(images).latent_dist
    if vae_noise is None:
        return dist.mean
    return (dist.mean + dist.std * vae_noise.to(dist.std.dtype)) * vae.config.scaling_factor


def render_gradient(vae, renders: torch.Tensor, size: tuple[int, int], vae_noise: torch.Tensor,
                    latent_grad: Callable[[torch.Tensor], torch.Tensor]) -> torch.Tensor:
    """dL/drenders [V, 3, H, W]: the renders resized to ``size`` and encoded with autograd on,
    ``latent_grad(z)`` (no grad) gives dL/dz, back-propagated through the encoder and the resize;
    non-finite entries zeroed. Free of host syncs (CUDA-graph capturable)."""
    with torch.enable_grad():
        x = renders.detach().requires_grad_(True)
        z = encode_latents(vae, resize(x, size), vae_noise)
        g = latent_grad(z.detach())
        (gx,) = torch.autograd.grad(z, x, grad_outputs=g.to(z.dtype))
    return torch.nan_to_num(gx, nan=0.0, posinf=0.0, neginf=0.0).contiguous()  # NCHW even for a channels-last VAE


def latent_shape(vae, n: int, size: tuple[int, int]) -> tuple[int, int, int, int]:
    f = vae_downsampling_factor(vae)
    return (n, int(vae.config.latent_channels), size[0] // f, size[1] // f)


def model_device_dtype(module: torch.nn.Module) -> tuple[torch.device, torch.dtype]:
    p = next(module.parameters())
    return p.device, p.dtype


def freeze(module: torch.nn.Module, device: torch.device | str | None = None,
           dtype: Optional[torch.dtype] = None, fused_norms: Optional[bool] = False) -> torch.nn.Module:
    """Moved/cast, eval() and no parameter gradients: SDS back-propagates to the input only.

    ``fused_norms``: True gives a diffusion model tiger's fused GroupNorm(+SiLU) and channels-last
    memory, None decides by :func:`.fused_norms.fused_norms_default` (a VAE or UNet on CUDA), False (the
    default, e.g. for text encoders) leaves it as is (:func:`.fused_norms.apply_fused_norms`).
    The cast uses ``torch.nn.Module.to`` (diffusers' override only adds a warning about
    float32-kept modules, which these models do not have)."""
    torch.nn.Module.to(module, device=device, dtype=dtype)
    module.eval()
    for p in module.parameters():
        p.requires_grad_(False)
    if fused_norms is not False:
        apply_fused_norms(module, fused_norms)
    return module


def _attention_probs_one_pass(self, query: torch.Tensor, key: torch.Tensor,
                              attention_mask: Optional[torch.Tensor] = None) -> torch.Tensor:
    """diffusers' ``Attention.get_attention_scores`` with the softmax run on the scores in their own
    dtype: torch's softmax of bfloat16/float16 input reduces and exponentiates in float32 and
    rounds its output once, which is what the upcast (``upcast_softmax``: scores to float32,
    softmax, back to the model's dtype) computes, without writing and reading the [B, L, L]
    scores three more times in float32 (forward and backward). Same values up to the order of the
    float32 sums; identical for float32 models. With ``ROW_SOFTMAX`` set on the layer, the softmax
    is :func:`tiger.ops.softmax.softmax_rows` (the same values up to float32 summation order)."""
    if self.upcast_attention:
        query, key = query.float(), key.float()
    if attention_mask is None:
        base, beta = query.new_empty(query.shape[0], query.shape[1], key.shape[1]), 0
    else:
        base, beta = attention_mask, 1
    scores = torch.baddbmm(base, query, key.transpose(-1, -2), beta=beta, alpha=self.scale)
    if self.__dict__.get(ROW_SOFTMAX, False):  # ModelKernels.row_softmax
        return softmax_rows(scores)
    return scores.softmax(dim=-1)


def matmul_vae_attention(vae: torch.nn.Module) -> int:
    """Run the VAE's attention layers as two batched matmuls and a softmax; returns how many.

    The Stable Diffusion VAE's mid-block attention has ONE head of width 512 over (H/f)·(W/f)
    tokens. Flash kernels stop at head width 256, so SDPA falls back to the memory-efficient
    kernel, whose backward alone took 16.9 ms of a 108 ms InstructPix2Pix step on the H100 (4
    renders at 512², 4096 tokens each; a torch.profiler trace of the guidance benchmark, see
    docs/BENCHMARKS.md).
    The score matrix is small here (4 × 4096² values), so the plain form costs a few GEMMs; its
    softmax runs on the scores in the model's dtype (:func:`_attention_probs_one_pass`: the VAE
    asks for a float32 upcast, four passes over the scores more per forward and backward).
    The SDS gradient back-propagates through the encoder every step, so this is the VAE's
    processor in both guidances; the UNets keep SDPA (their heads are 40–160 wide)."""
    require_diffusers("switching the VAE's attention processor")
    from diffusers.models.attention_processor import Attention, AttnProcessor

    layers = [m for m in vae.modules() if isinstance(m, Attention)]
    for m in layers:
        m.set_processor(AttnProcessor())
        m.get_attention_scores = types.MethodType(_attention_probs_one_pass, m)
    return len(layers)


def set_row_softmax(vae: torch.nn.Module, on: bool) -> int:
    """The softmax of the VAE's matmul attentions (:func:`matmul_vae_attention`) by
    :func:`tiger.ops.softmax.softmax_rows` (``on``) or torch's; returns how many layers use tiger's."""
    count = 0
    for m in vae.modules():
        if getattr(m.__dict__.get("get_attention_scores"), "__func__", None) is _attention_probs_one_pass:
            m.__dict__[ROW_SOFTMAX] = bool(on)
            count += bool(on)
    return count


class PromptEncoder:
    """Runs a text encoder once per prompt and keeps the embeddings; ``release()`` frees the encoder.

    The tokenizer pads to its ``model_max_length`` (77) with its own pad token; the embeddings are
    the encoder's ``last_hidden_state`` [n, 77, D] (for SD-2/MVDream the encoder holds the
    penultimate OpenCLIP layers, so that is the penultimate layer's output after ``ln_final``).
    """

    def __init__(self, tokenizer, text_encoder, device: torch.device | str, dtype: torch.dtype) -> None:
        self.tokenizer = tokenizer
        self.text_encoder = text_encoder
        self.device, self.dtype = torch.device(device), dtype
        self._cache: dict[str, torch.Tensor] = {}

    @torch.no_grad()
    def __call__(self, prompts: list[str]) -> torch.Tensor:
        missing = [p for p in dict.fromkeys(prompts) if p not in self._cache]
        if missing:
            if self.text_encoder is None:
                raise RuntimeError(f"tiger.edit: the text encoder was released; cannot encode new prompts {missing}")
            tok = self.tokenizer(missing, padding="max_length", max_length=self.tokenizer.model_max_length,
                                 truncation=True, return_tensors="pt")
            enc_device = next(self.text_encoder.parameters()).device
            out = self.text_encoder(tok.input_ids.to(enc_device)).last_hidden_state
            for p, e in zip(missing, out):
                self._cache[p] = e.to(self.device, self.dtype)
        return torch.stack([self._cache[p] for p in prompts])

    def release(self) -> None:
        """Drop the text encoder (its embeddings stay cached)."""
        self.text_encoder = None
        if self.device.type == "cuda":
            torch.cuda.empty_cache()


__all__ = ["PromptEncoder", "encode_latents", "freeze", "is_channels_last", "latent_shape", "matmul_vae_attention",
           "model_device_dtype", "render_gradient", "resize", "resolution_for", "vae_downsampling_factor"]
