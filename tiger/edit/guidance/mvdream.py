"""MVDream multi-view score distillation (paper §3.2 and appendix, SPEC §6).

Model: SD-2.1-base UNet whose self-attention runs jointly over the 4 views
(:mod:`.mvdream_attention`) plus a camera MLP added to the timestep embedding (diffusers'
``class_embed_type="projection"``, cameras passed as ``class_labels``). Loaded from the original
``sd-v2.1-base-4view.pt`` (via :mod:`.ldm_checkpoint`) or a diffusers folder.

Per step (the official 3D-generation setting with ``max_step_percent = 0.2``): the 4 renders are
resized to 256x256, encoded (posterior sample × scaling factor); ONE t for the 4 views; 2 branches
(prompt, negative prompt) with guidance scale 50; reconstruction form: ``x0`` predicted from the
guided ε, its standard deviation over the 4-view group rescaled toward that of the text-conditional
(un-guided) prediction's x0 (factor 0.5), loss ``0.5·‖z − x0‖² / 4`` → ``dL/dz = (z − x0) / 4``;
plain SDS ``w(t)(ε̂ − ε) / 4`` with ``recon=False``.

MVDream is never loaded for runs that do not use it: pass a loader (``from_registry`` does) and
the weights are read on the first ``grad`` call; ``release()`` frees them once λ2 reaches 0.
"""
from __future__ import annotations

import json
import logging
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Optional, Union

import torch

from tiger.models.paths import ConfigLike, PathLike, resolve_model_path
from tiger.utils.lazy import require, require_diffusers

from .base import GuidanceInfo, ViewBatch, check_render_shape, check_render_values, dtype_name
from .branch_prefix import BranchShare, shared_branches
from .cuda_graph import GraphedStep
from .diffusers_models import (PromptEncoder, freeze, latent_shape, matmul_vae_attention, model_device_dtype,
                               render_gradient)
from .model_kernels import ModelKernels, apply_model_kernels
from .ldm_checkpoint import ConfigSource, convert_ldm_checkpoint
from .mvdream_attention import install_multiview_attention
from .mvdream_cameras import mvdream_cameras
from .noise_schedule import NoiseSchedule, check_t_range, draw_noise, finite_clamped
from .text_kv import branch_text

logger = logging.getLogger(__name__)

NUM_VIEWS = 4
GUIDANCE_SCALE = 50.0
RECON_STD_RESCALE = 0.5
IMAGE_SIZE = 256
# MVDream-threestudio's configs/mvdream-sd21.yaml negative prompt.
NEGATIVE_PROMPT = ("ugly, bad anatomy, blurry, pixelated obscure, unnatural colors, poor lighting, dull, and unclear, "
                   "cropped, lowres, low quality, artifacts, duplicate, morbid, mutilated, poorly drawn face, deformed, "
                   "dehydrated, bad proportions")
CHECKPOINT_NAME = "sd-v2.1-base-4view.pt"
LDM_CONFIG_NAMES = ("sd-v2-base.json", "sd-v2-base.yaml")


@dataclass
class MVDreamModels:
    """UNet (multi-view attention installed, camera embedding), VAE (encoder used), prompt encoder, schedule."""

    unet: torch.nn.Module
    vae: torch.nn.Module
    prompts: PromptEncoder
    schedule: NoiseSchedule
    num_views: int = NUM_VIEWS


def _build_from_state(make: Callable[[], torch.nn.Module], state: dict[str, torch.Tensor], what: str,
                      position_ids: bool = False) -> torch.nn.Module:
    """``make()`` on the meta device, given the converted weights (no random init: 865M parameters
    in the UNet, 340M in the text tower). ``position_ids``: the model's ``position_ids`` buffers,
    which no checkpoint stores, are made here as 0, 1, 2, ... (CLIP's text tower)."""
    with torch.device("meta"):
        model = make()
    result = model.load_state_dict(state, strict=False, assign=True)
    missing = [k for k in result.missing_keys if not (position_ids and k.endswith("position_ids"))]
    if missing or result.unexpected_keys:
        raise ValueError(f"tiger.edit.mvdream: the checkpoint's {what} does not match its config: missing "
                         f"{missing[:5]}, unexpected {result.unexpected_keys[:5]}")
    for name, buf in list(model.named_buffers()) if position_ids else ():
        if name.endswith("position_ids") and buf.is_meta:  # [1, max_positions]
            owner = model.get_submodule(name.rpartition(".")[0])
            owner.register_buffer("position_ids", torch.arange(buf.shape[-1]).expand(1, -1), persistent=False)
    if any(t.is_meta for t in list(model.parameters()) + list(model.buffers())):
        raise ValueError(f"tiger.edit.mvdream: {what} has tensors the checkpoint does not provide")
    return model


def _load_state_dict(path: Path) -> dict[str, torch.Tensor]:
    """A tensors-only checkpoint, memory-mapped when it is in the zip format (legacy files are read)."""
    try:
        return torch.load(path, map_location="cpu", weights_only=True, mmap=True)
    except RuntimeError:  # pre-zip serialization cannot be memory-mapped
        return torch.load(path, map_location="cpu", weights_only=True)


def _tokenizer(folder: Optional[Path], checkpoint_dir: Path):
    """OpenCLIP's tokenizer: CLIP's BPE, padded with token 0 ('!'), 77 tokens. From ``folder``,
    ``<checkpoint dir>/tokenizer`` or the ``clip`` registry model (the same vocabulary)."""
    transformers = require("transformers", purpose="MVDream's tokenizer")
    if folder is None:
        local = checkpoint_dir / "tokenizer"
        folder = local if local.is_dir() else resolve_model_path("clip")
    return transformers.CLIPTokenizer.from_pretrained(str(folder), local_files_only=True, pad_token="!",
                                                      model_max_length=77)


def load_mvdream(
    path: PathLike | None = None,
    *,
    device: str | torch.device = "cpu",
    dtype: torch.dtype = torch.float32,
    config: ConfigLike = None,
    allow_download: bool = False,
    ldm_config: ConfigSource = None,
    tokenizer: PathLike | None = None,
    fused_norms: Optional[bool] = None,
) -> MVDreamModels:
    """Load MVDream (registry name ``mvdream``): the original LDM checkpoint or a diffusers folder.

    For the ``.pt``, the LDM config is ``ldm_config`` (mapping, .json or .yaml), else a
    ``sd-v2-base.json``/``.yaml`` beside the checkpoint, else MVDream's sd-v2-base; the tokenizer is
    ``tokenizer``, else ``tokenizer/`` beside the checkpoint, else the ``clip`` model's (same BPE).
    ``fused_norms``: as for :func:`.ip2p.load_ip2p` (True: both models; None: both on CUDA; False: neither).
    """
    found = resolve_model_path("mvdream", path, config=config, allow_download=allow_download)
    diffusers = require_diffusers("loading MVDream")
    transformers = require("transformers", purpose="loading MVDream's text encoder")
    if found.is_dir() and (found / CHECKPOINT_NAME).is_file() and not (found / "unet" / "config.json").is_file():
        found = found / CHECKPOINT_NAME
    if found.is_file():
        if ldm_config is None:
            ldm_config = next((found.parent / n for n in LDM_CONFIG_NAMES if (found.parent / n).is_file()), None)
        state = _load_state_dict(found)
        comp = convert_ldm_checkpoint(state, ldm_config)
        unet = _build_from_state(lambda: diffusers.UNet2DConditionModel(**comp.unet_config), comp.unet_state, "UNet")
        vae = _build_from_state(lambda: diffusers.AutoencoderKL(**comp.vae_config), comp.vae_state, "VAE")
        text_encoder = _build_from_state(
            lambda: transformers.CLIPTextModel(transformers.CLIPTextConfig(**comp.text_config)), comp.text_state,
            "text tower", position_ids=True)
        tok = _tokenizer(Path(tokenizer) if tokenizer is not None else None, found.parent)
        schedule = comp.schedule
    else:
        unet = diffusers.UNet2DConditionModel.from_pretrained(str(found), subfolder="unet", local_files_only=True)
        vae = diffusers.AutoencoderKL.from_pretrained(str(found), subfolder="vae", local_files_only=True)
        text_encoder = transformers.CLIPTextModel.from_pretrained(str(found / "text_encoder"), local_files_only=True)
        tok = transformers.CLIPTokenizer.from_pretrained(str(found / "tokenizer"), local_files_only=True)
        schedule = NoiseSchedule.from_scheduler_config(json.loads((found / "scheduler" / "scheduler_config.json").read_text()))
    if unet.config.class_embed_type != "projection" or not unet.config.projection_class_embeddings_input_dim:
        raise ValueError(f"tiger.edit.mvdream: {found} has no camera embedding (class_embed_type='projection')")
    install_multiview_attention(unet, NUM_VIEWS)
    vae.decoder = None
    vae.post_quant_conv = None
    logger.info("loaded MVDream from %s (%s, %s)", found, device, dtype)
    return MVDreamModels(
        unet=freeze(unet, device, dtype, fused_norms), vae=freeze(vae, device, dtype, fused_norms),
        prompts=PromptEncoder(tok, freeze(text_encoder, device), device, dtype), schedule=schedule.to(device))


class MVDreamGuidance:
    """SDS gradient of MVDream on exactly 4 rendered views (module docstring).

    Args:
        models: :class:`MVDreamModels`, or a zero-argument loader called on the first ``grad``.
        prompt: the text describing the edited object (encoded once with ``negative_prompt``); the
            guidance's ``instruction``.
        guidance_scale: classifier-free guidance scale (50).
        t_range: fractions of the schedule for t, one t for the 4 views (paper: max 0.2).
        image_size: the square size renders are resized to (256).
        recon: reconstruction-form gradient (official 3D setting); False: plain SDS ``w(t)(ε̂ − ε)``.
        recon_std_rescale: the x0 std rescale factor (0.5).
        grad_clip, cuda_graph, generator, collect_stats, keep_text_encoder, kernels: as for
            InstructPix2Pix (the kernels are put on the models when they are loaded).
        models_dtype: the dtype a loader (``models`` a callable) loads with, recorded by
            :meth:`settings` before the first load (:meth:`from_registry` passes its ``dtype``).
    """

    name = "mvdream"

    def __init__(self, models: Union[MVDreamModels, Callable[[], MVDreamModels]], prompt: str, *,
                 negative_prompt: str = NEGATIVE_PROMPT, guidance_scale: float = GUIDANCE_SCALE,
                 t_range: tuple[float, float] = (0.02, 0.2), image_size: int = IMAGE_SIZE, recon: bool = True,
                 recon_std_rescale: float = RECON_STD_RESCALE, grad_clip: Optional[float] = None,
                 cuda_graph: bool = False, generator: Optional[torch.Generator] = None,
                 collect_stats: bool = False, keep_text_encoder: bool = False,
                 models_dtype: Optional[torch.dtype] = None, kernels: Optional[ModelKernels] = None) -> None:
        if not isinstance(prompt, str) or not prompt.strip():
            raise ValueError("tiger.edit.mvdream: the prompt must be a non-empty string")
        if image_size <= 0:
            raise ValueError(f"tiger.edit.mvdream: image_size must be positive, got {image_size}")
        self.instruction, self.negative_prompt = prompt, negative_prompt
        self.guidance_scale = float(guidance_scale)
        self.t_range = check_t_range(t_range)
        self.image_size = int(image_size)
        self.recon, self.recon_std_rescale = bool(recon), float(recon_std_rescale)
        self.grad_clip, self.generator, self.collect_stats = grad_clip, generator, collect_stats
        self.keep_text_encoder = keep_text_encoder
        self.cuda_graph = cuda_graph
        self.kernels = kernels if kernels is not None else ModelKernels()
        self._loader = None if isinstance(models, MVDreamModels) else models
        self.models: Optional[MVDreamModels] = None
        self._graphed: Optional[GraphedStep] = None
        self._camera_cache: dict[tuple, torch.Tensor] = {}
        # the dtype recorded in settings(): fixed now, so loading later does not change the record
        self._settings_dtype = model_device_dtype(models.unet)[1] if isinstance(models, MVDreamModels) else models_dtype
        if isinstance(models, MVDreamModels):
            self._setup(models)

    @classmethod
    def from_registry(cls, prompt: str, path: PathLike | None = None, *, device: str | torch.device = "cpu",
                      dtype: torch.dtype = torch.float32, config: ConfigLike = None, allow_download: bool = False,
                      lazy: bool = True, fused_norms: Optional[bool] = None, **kwargs) -> "MVDreamGuidance":
        """Resolve ``mvdream`` now (a missing model fails here), load it on first use when ``lazy``."""
        resolve_model_path("mvdream", path, config=config, allow_download=allow_download)

        def loader() -> MVDreamModels:
            return load_mvdream(path, device=device, dtype=dtype, config=config, allow_download=allow_download,
                                fused_norms=fused_norms)

        return cls(loader if lazy else loader(), prompt, models_dtype=dtype, **kwargs)

    @property
    def loaded(self) -> bool:
        return self.models is not None

    def _setup(self, models: MVDreamModels) -> None:
        self.models = models
        self.device, self.dtype = model_device_dtype(models.unet)
        if self.cuda_graph and self.device.type != "cuda":
            raise ValueError("tiger.edit.mvdream: cuda_graph=True needs the models on a CUDA device")
        matmul_vae_attention(models.vae)
        apply_model_kernels(models.unet, models.vae, self.kernels)
        self.text_embeddings = models.prompts([self.instruction, self.negative_prompt]).to(self.dtype)  # [2, 77, D]
        if not self.keep_text_encoder:
            models.prompts.release()
        self._graphed = GraphedStep(self.step) if self.cuda_graph else None

    def load(self) -> MVDreamModels:
        """Load the models now (if built with a loader) and return them."""
        if self.models is None:
            if self._loader is None:
                raise RuntimeError("tiger.edit.mvdream: the models were released and there is no loader")
            self._setup(self._loader())
        return self.models

    def release(self) -> None:
        """Free the models (e.g. once λ2 reached 0); a later ``grad`` reloads them through the loader."""
        self.models = None
        self._graphed = None
        if torch.cuda.is_available():
            torch.cuda.empty_cache()

    def settings(self) -> dict[str, Any]:
        """What decides the gradients besides the prompt: negative prompt, CFG scale, noise range,
        resolution, gradient form, clamp, the models' dtype and kernels, and CUDA-graph use."""
        return {"negative_prompt": self.negative_prompt, "guidance_scale": self.guidance_scale,
                "t_range": list(self.t_range), "image_size": self.image_size, "recon": self.recon,
                "recon_std_rescale": self.recon_std_rescale, "grad_clip": self.grad_clip,
                "dtype": dtype_name(self._settings_dtype), "cuda_graph": bool(self.cuda_graph),
                "kernels": self.kernels.settings()}

    def generators(self) -> list[torch.Generator]:
        """The generator of t and the noises (none when drawing from the global one)."""
        return [] if self.generator is None else [self.generator]

    def reset_caches(self) -> None:
        """Forget the camera conditions cached by view ids (when the ids name other cameras)."""
        self._camera_cache.clear()

    # -- pieces -------------------------------------------------------------------------------
    def step(self, renders: torch.Tensor, cameras: torch.Tensor, t: torch.Tensor, noise: torch.Tensor,
             vae_noise: torch.Tensor) -> torch.Tensor:
        """dL/drenders for given camera conditions [V, 16], t [1] (shared), noise and VAE noise [V, c, h, w].

        Deterministic and free of host syncs (CUDA-graph capturable)."""
        return render_gradient(self.models.vae, renders, (self.image_size, self.image_size), vae_noise,
                               lambda z: self.latent_grad(z, cameras, t, noise))

    @torch.no_grad()
    def latent_grad(self, z: torch.Tensor, cameras: torch.Tensor, t: torch.Tensor, noise: torch.Tensor) -> torch.Tensor:
        """dL/dz [V, c, h, w] float32: the 2-branch multi-view UNet call, CFG and the gradient form."""
        m = self.models
        v = z.shape[0]
        tt = t.reshape(1).expand(v)
        z_t = m.schedule.add_noise(z, noise, tt)
        # branches: prompt, negative prompt: one tensor kept across calls (.text_kv)
        emb = branch_text(self, self.text_embeddings, (v, v))
        cams = torch.cat([cameras, cameras]).to(self.dtype)
        with shared_branches(m.unet, BranchShare(v, v)):  # both branches agree until text enters
            eps = m.unet(torch.cat([z_t, z_t]), torch.cat([tt, tt]), encoder_hidden_states=emb,
                         class_labels=cams).sample.float()
        e_text, e_unc = eps.chunk(2)
        eps_hat = e_unc + self.guidance_scale * (e_text - e_unc)
        if self.recon:
            x0 = m.schedule.predict_x0(z_t, eps_hat, tt)
            if self.recon_std_rescale > 0:
                x0_text = m.schedule.predict_x0(z_t, e_text, tt)
                factor = (x0_text.std() + 1e-8) / (x0.std() + 1e-8)
                x0 = self.recon_std_rescale * (x0 * factor) + (1.0 - self.recon_std_rescale) * x0
            g = z.float() - x0
        else:
            g = m.schedule.sds_weight(tt) * (eps_hat - noise.float())
        return finite_clamped(g, self.grad_clip) / v

    def prepare(self, views: ViewBatch) -> list[torch.Tensor]:
        """Cache the camera conditions of pooled ``views`` (with ``view_ids``) ahead of their
        step; returns them ([] for fresh views, converted in their step, and before the models are
        loaded: a worker thread does not load them)."""
        return [] if views.view_ids is None or not self.loaded else [self.camera_conditions(views)]

    def camera_conditions(self, views: ViewBatch) -> torch.Tensor:
        """[4, 16] MVDream cameras of the batch (needs ``views.object_center``), on the models'
        device; cached by ``views.view_ids`` (with the centre and up they were built for) when
        given: a pooled camera set costs its host-side conversion once, not in every step while
        the GPU waits for the step's launch."""
        if views.object_center is None:
            raise ValueError("tiger.edit.mvdream: views.object_center is required (MVDream's cameras are "
                             "relative to the object)")
        if len(views.cameras) != NUM_VIEWS:
            raise ValueError(f"tiger.edit.mvdream: needs exactly {NUM_VIEWS} cameras, got {len(views.cameras)}")
        key = None
        if views.view_ids is not None:
            frame = [views.object_center] + ([] if views.world_up is None else [views.world_up])
            key = (tuple(int(i) for i in views.view_ids.reshape(-1).tolist()),
                   *(tuple(torch.as_tensor(f, dtype=torch.float64).reshape(-1).tolist()) for f in frame))
            if key in self._camera_cache:
                return self._camera_cache[key]
        cams = mvdream_cameras(views.cameras, views.object_center, views.world_up).to(self.device)
        if key is not None:
            self._camera_cache[key] = cams
        return cams

    # -- Guidance protocol --------------------------------------------------------------------
    def grad(self, renders: torch.Tensor, views: ViewBatch, *, t: Optional[torch.Tensor] = None,
             noise: Optional[torch.Tensor] = None, vae_noise: Optional[torch.Tensor] = None
             ) -> tuple[torch.Tensor, GuidanceInfo]:
        """dL/drenders [4, 3, H, W]; ``t`` ([1]), ``noise``, ``vae_noise`` fix the random draws (tests)."""
        check_render_shape(renders, self.name, views=NUM_VIEWS)
        start = time.perf_counter()
        self.load()
        cams = self.camera_conditions(views)
        shape = latent_shape(self.models.vae, NUM_VIEWS, (self.image_size, self.image_size))
        if t is None:
            t = self.models.schedule.sample(1, self.t_range, self.generator, self.device)
        t = t.to(self.device, torch.long).reshape(1)
        noise = draw_noise(noise, shape, "mvdream.noise", self.generator, self.device)
        vae_noise = draw_noise(vae_noise, shape, "mvdream.vae_noise", self.generator, self.device)
        x = renders.to(self.device, torch.float32)
        check_render_values(renders, self.name)  # the read-back last: the step is launched right after
        run = self._graphed if self._graphed is not None else self.step
        g = run(x, cams, t, noise, vae_noise).to(renders.device, renders.dtype)
        info = GuidanceInfo(t=t, timings_ms={"total": 1e3 * (time.perf_counter() - start)})
        if self.collect_stats:
            info.extra["grad_norm"] = float(g.float().norm())
        return g, info
