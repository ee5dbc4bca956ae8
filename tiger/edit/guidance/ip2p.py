"""InstructPix2Pix score distillation (paper §3.2, SPEC §6).

Model: ``timbrooks/instruct-pix2pix`` in the diffusers folder layout (``unet/`` with
in_channels 8, ``vae/``, ``text_encoder/``, ``tokenizer/``, ``scheduler/``).

Per step and view v: render → bilinear resize (shorter side 512, multiples of the VAE's
downsampling factor) → latents ``z = sample(VAE(2x−1))·scaling_factor``; image condition
``c = mode(VAE(2·original−1))`` (not scaled; cached per camera id, or for views without ids
encoded inside the step, so it joins the step's CUDA graph); ``t_v`` uniform in
``t_range`` of the schedule; one UNet call on the 3 branches (image conditions
[c, c, 0], texts [instruction, "", ""]) gives ``ε̂ = ε_u + S_T(ε_text − ε_img) + S_I(ε_img − ε_u)``;
the latent gradient ``w(t)(ε̂ − ε)`` (non-finite zeroed, optionally clamped) is divided by V and
back-propagated through the VAE encoder and the resize to the renders.
"""
from __future__ import annotations

import json
import logging
import time
from dataclasses import dataclass
from typing import Any, Optional

import torch

from tiger.models.paths import ConfigLike, PathLike, resolve_model_path
from tiger.utils.lazy import require, require_diffusers

from .base import GuidanceInfo, ViewBatch, check_render_shape, check_render_values, dtype_name
from .branch_prefix import BranchShare, shared_branches
from .cuda_graph import GraphedStep
from .diffusers_models import (PromptEncoder, encode_latents, freeze, latent_shape, matmul_vae_attention,
                               model_device_dtype, render_gradient, resize, resolution_for, vae_downsampling_factor)
from .model_kernels import ModelKernels, apply_model_kernels
from .noise_schedule import NoiseSchedule, check_t_range, draw_noise, finite_clamped
from .text_kv import branch_text

logger = logging.getLogger(__name__)

TEXT_SCALE = 7.5   # S_T, InstructPix2Pix's default (paper appendix)
IMAGE_SCALE = 1.5  # S_I


@dataclass
class IP2PModels:
    """The InstructPix2Pix pieces a guidance needs: UNet (8 input channels), VAE (encoder used),
    the prompt encoder (text encoder + tokenizer, freed after use) and the noise schedule."""

    unet: torch.nn.Module
    vae: torch.nn.Module
    prompts: PromptEncoder
    schedule: NoiseSchedule


def load_ip2p(
    path: PathLike | None = None,
    *,
    device: str | torch.device = "cpu",
    dtype: torch.dtype = torch.float32,
    config: ConfigLike = None,
    allow_download: bool = False,
    fused_norms: Optional[bool] = None,
) -> IP2PModels:
    """Load InstructPix2Pix from a diffusers folder (registry name ``ip2p``), offline.

    UNet and VAE are cast to ``dtype``; the text encoder runs in float32 on ``device`` and is
    freed once the guidance has encoded its prompts. The VAE decoder is dropped (SDS only encodes).
    ``fused_norms``: True gives UNet and VAE tiger's fused GroupNorm(+SiLU) and channels-last memory
    (:func:`.fused_norms.apply_fused_norms`); None (default): both, on CUDA
    (:func:`.fused_norms.fused_norms_default` says why); False: neither.
    """
    folder = resolve_model_path("ip2p", path, config=config, allow_download=allow_download)
    diffusers = require_diffusers("loading InstructPix2Pix")
    transformers = require("transformers", purpose="loading InstructPix2Pix's text encoder")
    unet = diffusers.UNet2DConditionModel.from_pretrained(str(folder), subfolder="unet", local_files_only=True)
    if unet.config.in_channels != 2 * unet.config.out_channels:
        raise ValueError(f"tiger.edit.ip2p: {folder / 'unet'} has in_channels={unet.config.in_channels}, "
                         f"out_channels={unet.config.out_channels}; InstructPix2Pix's UNet takes the noisy "
                         f"latents and the image condition (in_channels = 2 x out_channels, 8)")
    vae = diffusers.AutoencoderKL.from_pretrained(str(folder), subfolder="vae", local_files_only=True)
    if vae.config.latent_channels != unet.config.out_channels:
        raise ValueError(f"tiger.edit.ip2p: VAE latent_channels={vae.config.latent_channels} does not match the "
                         f"UNet's out_channels={unet.config.out_channels} in {folder}")
    vae.decoder = None
    vae.post_quant_conv = None
    text_encoder = transformers.CLIPTextModel.from_pretrained(str(folder / "text_encoder"), local_files_only=True)
    tokenizer = transformers.CLIPTokenizer.from_pretrained(str(folder / "tokenizer"), local_files_only=True)
    sched_cfg = json.loads((folder / "scheduler" / "scheduler_config.json").read_text())
    models = IP2PModels(
        unet=freeze(unet, device, dtype, fused_norms),
        vae=freeze(vae, device, dtype, fused_norms),
        prompts=PromptEncoder(tokenizer, freeze(text_encoder, device), device, dtype),
        schedule=NoiseSchedule.from_scheduler_config(sched_cfg).to(device),
    )
    logger.info("loaded InstructPix2Pix from %s (%s, %s)", folder, device, dtype)
    return models


class InstructPix2PixGuidance:
    """SDS gradient of InstructPix2Pix on V rendered views (any V; V = 4 in CSD).

    Args:
        models: from :func:`load_ip2p` (or :meth:`from_registry`).
        instruction: the edit text (encoded once, with the empty prompt; then the encoder is freed
            unless ``keep_text_encoder``).
        text_scale, image_scale: S_T, S_I of the 3-branch classifier-free guidance.
        t_range: fractions of the schedule t is drawn from, per view (paper: [0.02, 0.2]).
        short_side: the shorter side renders are resized to (512).
        grad_clip: clamp of the latent gradient (None: no clamp).
        cuda_graph: replay the step (VAE encode, UNet, VAE backward; the condition encode too for
            views without ids) as a CUDA graph, and the condition encode of pooled views as a graph of
            its own (one launch from the view pool's worker thread instead of ~170) (CUDA only).
        generator: RNG for t and the noises (None: the global one).
        collect_stats: put the gradient's norm in ``info.extra['grad_norm']`` (one host sync per call).
        kernels: how UNet and VAE compute (:class:`.model_kernels.ModelKernels`: FP8 matmuls,
            opt-in; the fused GEGLU and the 4x4 VAE downsampling, on by default on CUDA), put on
            ``models`` now.
    """

    name = "ip2p"

    def __init__(self, models: IP2PModels, instruction: str, *, text_scale: float = TEXT_SCALE,
                 image_scale: float = IMAGE_SCALE, t_range: tuple[float, float] = (0.02, 0.2),
                 short_side: int = 512, grad_clip: Optional[float] = None, cuda_graph: bool = False,
                 generator: Optional[torch.Generator] = None, collect_stats: bool = False,
                 keep_text_encoder: bool = False, kernels: Optional[ModelKernels] = None) -> None:
        if not isinstance(instruction, str) or not instruction.strip():
            raise ValueError("tiger.edit.ip2p: the instruction must be a non-empty string")
        self.models = models
        self.instruction = instruction
        self.text_scale, self.image_scale = float(text_scale), float(image_scale)
        self.t_range = check_t_range(t_range)
        if short_side <= 0:
            raise ValueError(f"tiger.edit.ip2p: short_side must be positive, got {short_side}")
        self.short_side = int(short_side)
        self.grad_clip = grad_clip
        self.generator = generator
        self.collect_stats = collect_stats
        self.device, self.dtype = model_device_dtype(models.unet)
        matmul_vae_attention(models.vae)
        self.kernels = kernels if kernels is not None else ModelKernels()
        apply_model_kernels(models.unet, models.vae, self.kernels)
        self.text_embeddings = models.prompts([instruction, ""]).to(self.dtype)  # [2, 77, D]
        if not keep_text_encoder:
            models.prompts.release()
        self._cond_cache: dict[tuple[int, int, int], torch.Tensor] = {}
        self._graphed = GraphedStep(self.step) if cuda_graph else None
        self._graphed_fresh = GraphedStep(self.fresh_step) if cuda_graph else None
        self._graphed_cond = GraphedStep(self.encode_condition) if cuda_graph else None  # pooled views' condition
        if cuda_graph and self.device.type != "cuda":
            raise ValueError("tiger.edit.ip2p: cuda_graph=True needs the models on a CUDA device")

    @property
    def cuda_graph(self) -> bool:
        """Whether each step replays as a CUDA graph."""
        return self._graphed is not None

    @classmethod
    def from_registry(cls, instruction: str, path: PathLike | None = None, *, device: str | torch.device = "cpu",
                      dtype: torch.dtype = torch.float32, config: ConfigLike = None,
                      allow_download: bool = False, fused_norms: Optional[bool] = None,
                      **kwargs) -> "InstructPix2PixGuidance":
        """Resolve ``ip2p`` (argument, model config, ``$TIGER_MODELS``), load it and build the guidance."""
        models = load_ip2p(path, device=device, dtype=dtype, config=config, allow_download=allow_download,
                           fused_norms=fused_norms)
        return cls(models, instruction, **kwargs)

    # -- pieces -------------------------------------------------------------------------------
    def resolution(self, height: int, width: int) -> tuple[int, int]:
        return resolution_for(height, width, self.short_side, vae_downsampling_factor(self.models.vae))

    @torch.no_grad()
    def condition_latents(self, originals: torch.Tensor, size: tuple[int, int],
                          view_ids: Optional[torch.Tensor] = None) -> torch.Tensor:
        """[V, c, h, w] posterior modes of the original renders, cached per (camera id, size)."""
        originals = originals.to(self.device)
        if view_ids is None:
            return encode_latents(self.models.vae, resize(originals.float(), size), None)
        ids = [int(i) for i in view_ids.reshape(-1).tolist()]
        if len(ids) != originals.shape[0]:
            raise ValueError(f"tiger.edit.ip2p: view_ids has {len(ids)} entries for {originals.shape[0]} views")
        missing = [k for k, i in enumerate(ids) if (i, *size) not in self._cond_cache]
        if missing:
            todo = originals[missing].float()
            graphed = self._graphed_cond is not None and todo.is_cuda and size == self.resolution(*todo.shape[-2:])
            lat = self._graphed_cond(todo) if graphed else encode_latents(self.models.vae, resize(todo, size), None)
            for k, z in zip(missing, lat):
                self._cond_cache[(ids[k], *size)] = z
        return torch.stack([self._cond_cache[(i, *size)] for i in ids])

    @torch.no_grad()
    def encode_condition(self, originals: torch.Tensor) -> torch.Tensor:
        """[V, c, h, w] posterior modes of ``originals`` [V, 3, H, W] (float32, in [0, 1]) at
        :meth:`resolution`; free of host syncs (what the condition's CUDA graph replays)."""
        return encode_latents(self.models.vae, resize(originals, self.resolution(*originals.shape[-2:])), None)

    def prepare(self, views: ViewBatch) -> list[torch.Tensor]:
        """Encode and cache the image conditions of pooled ``views`` (with ``view_ids`` and
        ``originals``) ahead of their step; returns the cached latents ([] for fresh views, whose
        condition is encoded inside their step)."""
        if views.view_ids is None or views.originals is None:
            return []
        check_render_shape(views.originals, self.name)
        size = self.resolution(*views.originals.shape[-2:])
        self.condition_latents(views.originals, size, views.view_ids)
        return [self._cond_cache[(int(i), *size)] for i in views.view_ids.reshape(-1).tolist()]

    def reset_caches(self) -> None:
        """Forget the cached image-condition latents (when the original renders change)."""
        self._cond_cache.clear()

    def settings(self) -> dict[str, Any]:
        """What decides the gradients besides the instruction: scales, noise range, resolution,
        clamp, the models' dtype and kernels, and whether the step replays as a CUDA graph."""
        return {"text_scale": self.text_scale, "image_scale": self.image_scale, "t_range": list(self.t_range),
                "short_side": self.short_side, "grad_clip": self.grad_clip, "dtype": dtype_name(self.dtype),
                "cuda_graph": self.cuda_graph, "kernels": self.kernels.settings()}

    def generators(self) -> list[torch.Generator]:
        """The generator of t and the noises (none when drawing from the global one)."""
        return [] if self.generator is None else [self.generator]

    def step(self, renders: torch.Tensor, cond: torch.Tensor, t: torch.Tensor, noise: torch.Tensor,
             vae_noise: torch.Tensor) -> torch.Tensor:
        """dL/drenders for given condition latents, timesteps [V], noise and VAE posterior noise.

        Deterministic and free of host syncs (CUDA-graph capturable). renders [V, 3, H, W] in [0, 1];
        cond, noise, vae_noise [V, c, h, w]; t [V] int64.
        """
        m = self.models
        f = vae_downsampling_factor(m.vae)
        size = (cond.shape[-2] * f, cond.shape[-1] * f)
        return render_gradient(m.vae, renders, size, vae_noise, lambda z: self.latent_grad(z, cond, t, noise))

    def fresh_step(self, renders: torch.Tensor, originals: torch.Tensor, t: torch.Tensor, noise: torch.Tensor,
                   vae_noise: torch.Tensor) -> torch.Tensor:
        """:meth:`step` with the image condition encoded from ``originals`` [V, 3, H, W] (float32, in
        [0, 1]) inside: views without camera ids (fresh every step) have nothing to cache, so the
        encode joins the step's CUDA graph instead of running eagerly before it. Same values as
        ``step(renders, condition_latents(originals, size), ...)``; free of host syncs."""
        f = vae_downsampling_factor(self.models.vae)
        size = (noise.shape[-2] * f, noise.shape[-1] * f)
        with torch.no_grad():
            cond = encode_latents(self.models.vae, resize(originals, size), None)
        return self.step(renders, cond, t, noise, vae_noise)

    @torch.no_grad()
    def latent_grad(self, z: torch.Tensor, cond: torch.Tensor, t: torch.Tensor, noise: torch.Tensor) -> torch.Tensor:
        """dL/dz [V, c, h, w] float32: the 3-branch UNet call, CFG and ``w(t)(ε̂ − ε) / V``."""
        m = self.models
        v = z.shape[0]
        z_t = m.schedule.add_noise(z, noise, t)
        cond3 = torch.cat([cond, cond, torch.zeros_like(cond)]).to(z_t.dtype)
        inp = torch.cat([torch.cat([z_t, z_t, z_t]), cond3], dim=1)
        # branches: instruction, "", "": one tensor kept across calls (its cross-attention keys and
        # values are computed once: .text_kv)
        emb = branch_text(self, self.text_embeddings, (v, 2 * v))
        with shared_branches(m.unet, BranchShare(v, v)):  # instruction and image-only rows agree until text enters
            eps = m.unet(inp, torch.cat([t, t, t]), encoder_hidden_states=emb).sample.float()
        e_text, e_img, e_unc = eps.chunk(3)
        eps_hat = e_unc + self.text_scale * (e_text - e_img) + self.image_scale * (e_img - e_unc)
        return finite_clamped(m.schedule.sds_weight(t) * (eps_hat - noise.float()), self.grad_clip) / v

    # -- Guidance protocol --------------------------------------------------------------------
    def grad(self, renders: torch.Tensor, views: ViewBatch, *, t: Optional[torch.Tensor] = None,
             noise: Optional[torch.Tensor] = None, vae_noise: Optional[torch.Tensor] = None
             ) -> tuple[torch.Tensor, GuidanceInfo]:
        """dL/drenders [V, 3, H, W] (renders' dtype and device). ``t``, ``noise``, ``vae_noise`` fix
        the random draws (tests); by default they come from ``generator``."""
        check_render_shape(renders, self.name)
        if views.originals is None or tuple(views.originals.shape) != tuple(renders.shape):
            got = None if views.originals is None else list(views.originals.shape)
            raise ValueError(f"tiger.edit.ip2p: views.originals must match renders {list(renders.shape)}, got {got}")
        start = time.perf_counter()
        v, _, h, w = renders.shape
        size = self.resolution(h, w)
        fresh = views.view_ids is None  # no ids: nothing to cache, the condition is encoded in the step
        cond = None if fresh else self.condition_latents(views.originals, size, views.view_ids)
        shape = latent_shape(self.models.vae, v, size)
        if t is None:
            t = self.models.schedule.sample(v, self.t_range, self.generator, self.device)
        noise = draw_noise(noise, shape, "ip2p.noise", self.generator, self.device)
        vae_noise = draw_noise(vae_noise, shape, "ip2p.vae_noise", self.generator, self.device)
        t = t.to(self.device, torch.long).reshape(v)
        x = renders.to(self.device, torch.float32)
        if fresh:
            originals = views.originals.to(self.device, torch.float32)
        check_render_values(renders, self.name)  # the read-back last: the step is launched right after
        if fresh:
            run = self._graphed_fresh if self._graphed_fresh is not None else self.fresh_step
            g = run(x, originals, t, noise, vae_noise)
        else:
            run = self._graphed if self._graphed is not None else self.step
            g = run(x, cond, t, noise, vae_noise)
        g = g.to(renders.device, renders.dtype)
        info = GuidanceInfo(t=t, timings_ms={"total": 1e3 * (time.perf_counter() - start)})
        if self.collect_stats:
            info.extra["grad_norm"] = float(g.float().norm())
        return g, info
