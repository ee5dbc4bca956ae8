"""FeatUp upsamplers for MaskCLIP features (SPEC §4): the implicit upsampler (per-image, the
paper's choice) and the JBU stack (fast, loads FeatUp's MaskCLIP checkpoint).

Implicit upsampler (FeatUp ``train_implicit_upsampler.py`` defaults): an MLP on Fourier features
of pixel coordinates and colour (30 frequencies, learned phase biases) predicts ``proj_dim`` =
128 PCA coefficients of the features at every pixel. It is fitted so that jittered
(pad/zoom/crop/flip) copies of its output, downsampled by a learned attention downsampler,
match the backbone's features of the identically jittered images (NAdam, 1200 steps, 10 jitters
per step, learned per-pixel uncertainty, magnitude, magnitude-TV and blur-pin regularisers).
Because the network is a function of (x, y, r, g, b), it is evaluated directly at the output
resolution.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Callable, Iterable

import torch
import torch.nn.functional as F
from torch import nn

from tiger.ops import cuda_enabled
from tiger.ops.jbu import adaptive_conv
from tiger.utils.filters import gaussian_blur
from tiger.utils.pca import fit_pca

logger = logging.getLogger(__name__)
# read once: a plain bool is what torch.compile can trace through (the library call is not)
_CUDA_KERNELS = cuda_enabled()

Featurizer = Callable[[torch.Tensor], torch.Tensor]  # images [B,3,H,W] in [0,1] -> [B,D,h,w]


# ----------------------------------------------------------------------------- JBU stack
class JBULearnedRange(nn.Module):
    """One x2 joint-bilateral upsampling stage (FeatUp's ``JBULearnedRange``; same parameter names,
    so FeatUp checkpoints load). The per-pixel kernel runs through ``tiger::adaptive_conv``."""

    def __init__(self, guidance_dim: int, feat_dim: int, key_dim: int, scale: int = 2, radius: int = 3) -> None:
        super().__init__()
        self.scale, self.radius, self.diameter = scale, radius, 2 * radius + 1
        self.guidance_dim, self.key_dim, self.feat_dim = guidance_dim, key_dim, feat_dim
        d2 = self.diameter**2
        self.range_temp = nn.Parameter(torch.tensor(0.0))
        self.range_proj = nn.Sequential(
            nn.Conv2d(guidance_dim, key_dim, 1, 1), nn.GELU(), nn.Dropout2d(0.1), nn.Conv2d(key_dim, key_dim, 1, 1)
        )
        self.fixup_proj = nn.Sequential(
            nn.Conv2d(guidance_dim + d2, d2, 1, 1), nn.GELU(), nn.Dropout2d(0.1), nn.Conv2d(d2, d2, 1, 1)
        )
        self.sigma_spatial = nn.Parameter(torch.tensor(1.0))

    def range_kernel(self, guidance: torch.Tensor) -> torch.Tensor:
        b, _, h, w = guidance.shape
        proj = self.range_proj(guidance)
        padded = F.pad(proj, [self.radius] * 4, mode="reflect")
        queries = F.unfold(padded, self.diameter).reshape(b, self.key_dim, self.diameter**2, h, w)
        temp = self.range_temp.exp().clamp(1e-4, 1e4)
        return F.softmax(temp * torch.einsum("bcphw,bchw->bphw", queries, proj), dim=1)

    def spatial_kernel(self) -> torch.Tensor:
        r = torch.linspace(-1, 1, self.diameter, device=self.sigma_spatial.device, dtype=self.sigma_spatial.dtype)
        y, x = torch.meshgrid(r, r, indexing="ij")
        k = torch.exp(-(x.square() + y.square()) / (2 * self.sigma_spatial**2))
        return k.reshape(1, self.diameter**2, 1, 1)

    def forward(self, source: torch.Tensor, guidance: torch.Tensor) -> torch.Tensor:
        b, _, gh, gw = guidance.shape
        if source.shape[0] != b:
            raise ValueError(f"tiger.JBU: source batch {source.shape[0]} != guidance batch {b}")
        kernel = self.range_kernel(guidance) * self.spatial_kernel()
        kernel = kernel / kernel.sum(1, keepdim=True).clamp(1e-7)
        kernel = kernel + 0.1 * self.fixup_proj(torch.cat([kernel, guidance], dim=1))
        kernel = kernel.permute(0, 2, 3, 1).reshape(b, gh, gw, self.diameter, self.diameter)
        hr = F.interpolate(source, (gh, gw), mode="bicubic", align_corners=False)
        hr = F.pad(hr, [self.radius] * 4, mode="reflect")
        return adaptive_conv(hr.contiguous(), kernel.contiguous())


class JBUStack(nn.Module):
    """FeatUp's JBU upsampler: four x2 stages guided by the image, then a residual 1x1 fix-up.

    ``forward(source [B, D, h, w], guidance [B, 3, H, W]) -> [B, D, 16h, 16w]``; the guidance is the
    normalised image (FeatUp: ImageNet statistics), average-pooled to each stage's size.
    """

    def __init__(self, feat_dim: int, key_dim: int = 32, radius: int = 3) -> None:
        super().__init__()
        self.up1, self.up2, self.up3, self.up4 = (JBULearnedRange(3, feat_dim, key_dim, radius=radius) for _ in range(4))
        self.fixup_proj = nn.Sequential(nn.Dropout2d(0.2), nn.Conv2d(feat_dim, feat_dim, kernel_size=1))

    @staticmethod
    def _stage(source: torch.Tensor, guidance: torch.Tensor, up: JBULearnedRange) -> torch.Tensor:
        h, w = source.shape[-2:]
        return up(source, F.adaptive_avg_pool2d(guidance, (2 * h, 2 * w)))

    def forward(self, source: torch.Tensor, guidance: torch.Tensor) -> torch.Tensor:
        for up in (self.up1, self.up2, self.up3, self.up4):
            source = self._stage(source, guidance, up)
        return self.fixup_proj(source) * 0.1 + source

    @classmethod
    def from_checkpoint(cls, path=None, feat_dim: int = 512, **kwargs) -> "JBUStack":
        """A JBU stack with FeatUp's MaskCLIP weights (see :func:`tiger.models.load_jbu_checkpoint`)."""
        from tiger.models.featup import load_jbu_checkpoint

        state = load_jbu_checkpoint(path, **kwargs)
        dim = state["fixup_proj.1.weight"].shape[0] if "fixup_proj.1.weight" in state else feat_dim
        model = cls(dim)
        model.load_state_dict(state, strict=True)
        return model.eval()


# ----------------------------------------------------------------------------- implicit upsampler
class FourierFeaturizer(nn.Module):
    """FeatUp's ``ImplicitFeaturizer`` (colour features, learned phase biases): sin/cos of
    (y, x, r, g, b) at ``n_freqs`` log-spaced frequencies exp(linspace(-2, 10)), plus the colour."""

    def __init__(self, n_freqs: int = 30, generator: torch.Generator | None = None) -> None:
        super().__init__()
        self.n_freqs, self.dims = n_freqs, 5
        self.biases = nn.Parameter(torch.randn(2, self.dims, n_freqs, generator=generator))

    @property
    def out_dim(self) -> int:
        return 2 * self.dims * self.n_freqs + 3

    def forward(self, image: torch.Tensor) -> torch.Tensor:
        b, _, h, w = image.shape
        gy = torch.linspace(-1, 1, h, device=image.device, dtype=image.dtype)
        gx = torch.linspace(-1, 1, w, device=image.device, dtype=image.dtype)
        yy, xx = torch.meshgrid(gy, gx, indexing="ij")
        coords = torch.stack([yy, xx]).unsqueeze(0).expand(b, 2, h, w)
        feats = torch.cat([coords, image], dim=1).unsqueeze(1)  # [B, 1, 5, H, W]
        freqs = torch.exp(torch.linspace(-2, 10, self.n_freqs, device=image.device, dtype=image.dtype))
        feats = feats * freqs.reshape(1, self.n_freqs, 1, 1, 1)  # [B, F, 5, H, W]
        # FeatUp reshapes its (2, 5, F) biases as (F, 5): kept for checkpoint-free parity of init.
        sin_b = self.biases[0].reshape(1, self.n_freqs, self.dims, 1, 1)
        cos_b = self.biases[1].reshape(1, self.n_freqs, self.dims, 1, 1)
        n = self.n_freqs * self.dims
        return torch.cat(
            [torch.sin(feats + sin_b).reshape(b, n, h, w), torch.cos(feats + cos_b).reshape(b, n, h, w), image], dim=1
        )

    def frequencies(self, device: torch.device | str, dtype: torch.dtype) -> torch.Tensor:
        """The ``n_freqs`` frequencies exp(linspace(-2, 10)) [F] (radians per unit of input)."""
        return torch.exp(torch.linspace(-2, 10, self.n_freqs, device=device, dtype=dtype))

    @staticmethod
    def pixel_inputs(image: torch.Tensor) -> torch.Tensor:
        """The five inputs of every pixel, (y, x, r, g, b) [B, H, W, 5]: the coordinates in
        [-1, 1] (top-left -1) and the colour of ``image`` [B, 3, H, W]."""
        b, _, h, w = image.shape
        gy = torch.linspace(-1, 1, h, device=image.device, dtype=image.dtype)
        gx = torch.linspace(-1, 1, w, device=image.device, dtype=image.dtype)
        yy, xx = torch.meshgrid(gy, gx, indexing="ij")
        colour = image.permute(0, 2, 3, 1)
        return torch.cat([torch.stack([yy, xx], -1).expand(b, h, w, 2), colour], -1)

    def pixels(self, image: torch.Tensor) -> torch.Tensor:
        """``forward`` with channels last: [B, 3, H, W] -> [B, H, W, out_dim], same channel order."""
        b, _, h, w = image.shape
        inputs = self.pixel_inputs(image)  # [B, H, W, 5]
        freqs = self.frequencies(image.device, image.dtype)
        feats = inputs.unsqueeze(-2) * freqs.view(self.n_freqs, 1)  # [B, H, W, F, 5]
        n = self.n_freqs * self.dims
        sin_b = self.biases[0].reshape(self.n_freqs, self.dims)
        cos_b = self.biases[1].reshape(self.n_freqs, self.dims)
        return torch.cat([torch.sin(feats + sin_b).reshape(b, h, w, n), torch.cos(feats + cos_b).reshape(b, h, w, n),
                          inputs[..., 2:]], -1)


class _ChannelNorm(nn.Module):
    def __init__(self, dim: int) -> None:
        super().__init__()
        self.norm = nn.LayerNorm(dim)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.norm(x.permute(0, 2, 3, 1)).permute(0, 3, 1, 2)


def _min_max(x: torch.Tensor) -> torch.Tensor:
    flat = x.transpose(0, 1).reshape(x.shape[1], -1)
    lo = flat.min(-1).values.view(1, -1, 1, 1)
    scale = (flat.max(-1).values.view(1, -1, 1, 1) - lo).clamp_min(1e-4)
    return (x - lo) / scale - 0.5


def _dropout_keep(p: float, shape: tuple[int, ...], like: torch.Tensor) -> torch.Tensor:
    """Channel dropout's multiplier of ``shape``: Bernoulli(1 - p) / (1 - p), drawn in ``like``'s
    dtype from its device's generator."""
    return like.new_empty(shape).bernoulli_(1 - p).div_(1 - p)


def fused_features_available(device: torch.device) -> bool:
    """Whether the implicit network's fused ops (``tiger::fourier_layer_norm``,
    ``tiger::relu_scale_layer_norm``) have kernels for ``device`` (CPU always; CUDA when the
    compiled core has its CUDA kernels)."""
    return device.type == "cpu" or (device.type == "cuda" and _CUDA_KERNELS)


class ImplicitNet(nn.Module):
    """FeatUp's implicit network: min-max scaled image -> Fourier features -> 3 1x1 convs.

    ``fused``: :meth:`forward_pixels` computes the Fourier features, the first LayerNorm and the
    first channel dropout in one op (``tiger::fourier_layer_norm``), and the hidden ReLU, channel
    dropout and LayerNorm in another (``tiger::relu_scale_layer_norm``), where the device has
    their kernels; else (and with ``fused=False``) as the PyTorch composition of :meth:`forward`.
    """

    def __init__(self, out_dim: int, n_freqs: int = 30, generator: torch.Generator | None = None,
                 dropout: float = 0.2, fused: bool = True) -> None:
        super().__init__()
        self.fourier = FourierFeaturizer(n_freqs, generator)
        self.fused = fused
        d = self.fourier.out_dim
        self.net = nn.Sequential(
            _ChannelNorm(d), nn.Dropout2d(dropout), nn.Conv2d(d, out_dim, 1), nn.ReLU(), nn.Dropout2d(dropout),
            _ChannelNorm(out_dim), nn.Conv2d(out_dim, out_dim, 1), nn.ReLU(), nn.Conv2d(out_dim, out_dim, 1),
        )

    def forward(self, image: torch.Tensor) -> torch.Tensor:
        return self.net(self.fourier(_min_max(image)))

    def forward_pixels(self, image: torch.Tensor) -> torch.Tensor:
        """``forward`` computed channels last, as a per-pixel MLP (LayerNorm over the contiguous
        last dimension, 1x1 convolutions as ``F.linear``, channel dropout as one mask per image
        and channel): no permuted copies. Returns [B, out_dim, H, W] (a channels-last view).

        With ``fused`` (and a kernel for the device), the Fourier features, the first LayerNorm
        and the first dropout are one op that writes its C channels once, in the autocast dtype
        when autocast is on (bf16 on CUDA in the fast fit), and recomputes the features in the
        backward; the hidden ReLU, dropout and LayerNorm are a second op, in the first linear
        layer's output dtype. The dropout masks are drawn in the same order and dtypes, so a
        seeded fit draws the same masks either way."""
        scaled = _min_max(image)
        if self.fused and fused_features_available(image.device):
            x = self._fused_input_layers(scaled)
            conv = self.net[2]
            x = self._fused_hidden_layers(F.linear(x, conv.weight.flatten(1), conv.bias))
            rest = list(self.net)[6:]
        else:
            x, rest = self.fourier.pixels(scaled), list(self.net)
        for layer in rest:
            if isinstance(layer, _ChannelNorm):
                x = layer.norm(x)
            elif isinstance(layer, nn.Conv2d):
                x = F.linear(x, layer.weight.flatten(1), layer.bias)
            elif isinstance(layer, nn.Dropout2d):
                if self.training and layer.p > 0:
                    x = x * _dropout_keep(layer.p, (x.shape[0], 1, 1, x.shape[-1]), x)
            else:
                x = layer(x)
        return x.permute(0, 3, 1, 2)

    def _fused_hidden_layers(self, x: torch.Tensor) -> torch.Tensor:
        """ReLU, channel dropout and LayerNorm of the first linear layer's output x [B, H, W, D]
        through ``tiger::relu_scale_layer_norm``, in x's dtype (bf16 under the fit's autocast,
        where the composition's LayerNorm runs in float32): [B, H, W, D]. The dropout mask is
        drawn as the composition draws it (x's dtype, the same shape)."""
        from tiger.ops.featup import relu_scale_layer_norm

        b, h, w, d = x.shape
        drop, norm = self.net[4], self.net[5].norm
        scale = None
        if self.training and drop.p > 0:
            scale = _dropout_keep(drop.p, (b, 1, 1, d), x).view(b, d).to(norm.weight.dtype)
        return relu_scale_layer_norm(x.reshape(b, h * w, d), norm.weight, norm.bias, scale, norm.eps).view(b, h, w, d)

    def _fused_input_layers(self, scaled: torch.Tensor) -> torch.Tensor:
        """Fourier features, LayerNorm and channel dropout of the min-max scaled image [B, 3, H, W]
        through ``tiger::fourier_layer_norm``: [B, H, W, C]."""
        from tiger.ops.featup import fourier_layer_norm

        b, _, h, w = scaled.shape
        norm, drop = self.net[0].norm, self.net[1]
        c = self.fourier.out_dim
        inputs = self.fourier.pixel_inputs(scaled).reshape(b, h * w, 5)
        scale = None
        if self.training and drop.p > 0:
            scale = _dropout_keep(drop.p, (b, c), scaled)
        dev = scaled.device.type
        out_dtype = torch.get_autocast_dtype(dev) if torch.is_autocast_enabled(dev) else None
        x = fourier_layer_norm(inputs, self.fourier.frequencies(scaled.device, scaled.dtype), self.fourier.biases,
                               norm.weight, norm.bias, scale, norm.eps, out_dtype)
        return x.view(b, h, w, c)


class AttentionDownsampler(nn.Module):
    """FeatUp's learned attention downsampler: each low-res cell is a softmax-weighted average of a
    ``kernel`` x ``kernel`` window of the (blurred) high-res features."""

    def __init__(self, dim: int, kernel: int, generator: torch.Generator | None = None,
                 dropout: float = 0.2) -> None:
        super().__init__()
        self.kernel, self.dropout = kernel, dropout
        self.attention = nn.Sequential(nn.Dropout(dropout), nn.Linear(dim, 1))
        self.w = nn.Parameter(torch.ones(kernel, kernel) + 0.01 * torch.randn(kernel, kernel, generator=generator))
        self.b = nn.Parameter(torch.zeros(kernel, kernel) + 0.01 * torch.randn(kernel, kernel, generator=generator))

    def forward(self, hr: torch.Tensor, size: tuple[int, int]) -> torch.Tensor:
        b, c, h, w = hr.shape
        fh, fw = size
        k = min(self.kernel, h, w)
        x = gaussian_blur(hr, 5, 1.0, padding="reflect")
        sh = max(1, (h - k) // max(fh - 1, 1))
        sw = max(1, (w - k) // max(fw - 1, 1))
        patches = F.unfold(x, k, stride=(sh, sw))  # [B, C*k*k, L]
        nh, nw = (h - k) // sh + 1, (w - k) // sw + 1
        patches = patches.reshape(b, c, k * k, nh, nw)[..., :fh, :fw].permute(0, 3, 4, 2, 1)  # [B,fh,fw,kk,C]
        logits = self.attention(patches).squeeze(-1)
        if self.training and self.dropout > 0:
            logits = logits * (torch.rand(logits.shape[:3] + (1,), device=hr.device) > self.dropout)
        wk = self.w[:k, :k].reshape(1, 1, 1, -1)
        bk = self.b[:k, :k].reshape(1, 1, 1, -1)
        attn = F.softmax(logits * wk + bk, dim=-1)
        return torch.einsum("bhwpc,bhwp->bchw", patches, attn)


@dataclass
class Jitter:
    """One FeatUp jitter: reflect-pad by ``pad``, zoom, crop at (y, x), optional horizontal flip."""

    pad: int
    zoom: float
    y: int
    x: int
    flip: bool

    def apply(self, img: torch.Tensor) -> torch.Tensor:
        h, w = img.shape[-2:]
        out = F.pad(img, [self.pad] * 4, mode="reflect") if self.pad > 0 else img
        if self.zoom > 1.0:
            out = F.interpolate(out, scale_factor=self.zoom, mode="bilinear", align_corners=False)
        out = out[..., self.y : self.y + h, self.x : self.x + w]
        return torch.flip(out, [3]) if self.flip else out


def sample_jitter(h: int, w: int, max_pad: int, max_zoom: float, use_flips: bool, gen: torch.Generator) -> Jitter:
    """FeatUp's ``sample_transform``: flip with p=0.5; zoom in [1, max_zoom) with p=0.5; a crop
    anywhere inside the padded, zoomed image."""
    u = torch.rand(3, generator=gen).tolist()
    flip = use_flips and u[0] > 0.5
    zoom = 1.0 + u[2] * (max_zoom - 1.0) if u[1] > 0.5 else 1.0
    vh = int((h + 2 * max_pad) * zoom) - h + 1
    vw = int((w + 2 * max_pad) * zoom) - w + 1
    y = int(torch.randint(0, max(vh, 1), (), generator=gen))
    x = int(torch.randint(0, max(vw, 1), (), generator=gen))
    return Jitter(max_pad, zoom, y, x, flip)


# The fast fit's default stopping rule (ImplicitConfig.stop_change, min_steps): the fit stops once
# 100 more steps move its map by less than 1 - cosine 1e-2, about what two stopped fits that differ
# only in their seed differ by (cosine 0.991 on the H100 at 1080p), and never before 400 steps, where
# the calibration's fits lie at cosine 0.993-0.994 from the 1200-step reference fit (0.990 at 300).
# Measured there: the change per 100 steps falls 1.2e-2 (300) -> 3.8e-3 / 7.6e-3 (400, two seeds)
# -> 3.6e-3 (500), then stays at 2-4e-3; stopping at 500 instead of 400 gains 0.001-0.002 of
# cosine for 25 % more time (docs/BENCHMARKS.md, "implicit FeatUp per 1080p image").
STOP_CHANGE = 1e-2
STOP_MIN_STEPS = 400


@dataclass
class ImplicitConfig:
    """FeatUp's implicit-upsampler defaults (``configs/implicit_upsampler.yaml``).

    ``max_pad`` is in pixels at a 224-pixel input and scales with the fitting resolution.
    ``channel_norm`` (FeatUp's ``use_norm``) LayerNorms the backbone features before fitting;
    it is off by default because it changes the CLIP features' cosine with text embeddings.
    ``dropout`` is FeatUp's rate for the network's channel dropout, the attention's input dropout
    and its logit mask. Those masks come from the device's own generator (drawing them on the
    CPU would cost more than the fit); every other random number (jitters, view picks,
    initial weights) comes from a CPU generator, so with ``dropout=0`` a fit on CUDA follows the
    CPU fit up to floating-point rounding.

    ``method``: ``"fast"`` (default; :mod:`tiger.language.featup_fit`: batched jitters, the
    downsampler without its patch tensor, no per-step host sync) or ``"reference"`` (the
    original loop, kept to check the fast fit against). ``precision``: ``"bf16"`` runs the
    network and the backbone passes of the fast fit under bf16 autocast on CUDA (float32 on the
    CPU either way); ``"fp32"`` keeps float32 everywhere. ``cuda_graph``: the fast fit on CUDA
    replays its step (forward, backward, NAdam) from one CUDA graph. ``compile_network``: the
    fast fit runs the network through ``torch.compile`` (fuses the Fourier features, LayerNorm,
    dropout and casts, the memory-bound part of the step; costs a compilation per process).
    ``fused_network``: the fast fit's network computes its Fourier features, first LayerNorm and
    first channel dropout in one op (``tiger::fourier_layer_norm``), writing the network's widest
    activation once in the autocast dtype and recomputing it in the backward, and its hidden
    ReLU, dropout and LayerNorm in another (where the device has the kernels; see
    :class:`ImplicitNet`).
    ``step_layout``: the fast fit's layout between the network and the attention op.
    ``"channels_last"`` (default) keeps the network's own layout: ``tiger::magnitude_blur`` takes
    each pixel's magnitude and blurs (magnitude, features) in one op, ``tiger::masked_logit``
    takes the attention logit of the dropped-out blurred map, and the attention op reads the
    blurred map in place. ``"channels_first"`` is the PyTorch composition (a float32
    channels-first copy, ``norm``, ``cat``, the depthwise reflect blur, ``F.dropout`` and a 1x1
    convolution, then a channels-last copy for the attention op). Both compute the same loss
    and gradients up to rounding; on the CPU they draw the same dropout masks (on CUDA
    ``F.dropout`` draws its mask with its own kernel, so the masks differ there).
    ``attention_variant``: the CUDA kernels of ``tiger::jittered_window_attention`` the fast fit
    uses (:data:`tiger.ops.featup.WINDOW_VARIANTS`; the CPU kernels are the same for all).

    ``steps`` is the most the fit runs (FeatUp's 1200). The fast fit stops earlier once the
    fitted map stops changing: every ``check_every`` steps (from ``min_steps`` on) it evaluates
    the network at the fitting resolution, projects it to the feature space and stops when the
    mean per-pixel cosine similarity with the previous check's map is above
    ``1 - stop_change`` (``stop_change=0`` runs every step). The loss is no stopping signal: its
    outlier term keeps falling after the map has settled. Views are featurised when a step
    first picks them, so the views that a stopped fit never picks cost nothing.
    """

    steps: int = 1200
    stop_change: float = STOP_CHANGE
    check_every: int = 100
    min_steps: int = STOP_MIN_STEPS
    n_views: int = 3000
    jitters_per_step: int = 10
    proj_dim: int = 128
    pca_batch: int = 50
    n_freqs: int = 30
    kernel_size: int = 29
    max_pad: int = 30
    max_zoom: float = 1.8
    use_flips: bool = True
    mag_weight: float = 0.001
    mag_tv_weight: float = 0.05
    blur_pin: float = 0.1
    lr: float = 2e-3
    channel_norm: bool = False
    dropout: float = 0.2
    featurize_batch: int = 256  # backbone batch (H100: 2048 views 0.77 s at 64, 0.69 s at 256)
    fused_network: bool = True
    seed: int = 0
    method: str = "fast"
    precision: str = "bf16"
    cuda_graph: bool = True
    compile_network: bool = False
    step_layout: str = "channels_last"
    attention_variant: str = "pixel_dots"

    def __post_init__(self) -> None:
        if self.method not in ("fast", "reference"):
            raise ValueError(f"tiger.ImplicitConfig: method must be 'fast' or 'reference', got {self.method!r}")
        if self.precision not in ("bf16", "fp32"):
            raise ValueError(f"tiger.ImplicitConfig: precision must be 'bf16' or 'fp32', got {self.precision!r}")
        if not 0.0 <= self.stop_change < 1.0:
            raise ValueError(f"tiger.ImplicitConfig: stop_change must be in [0, 1), got {self.stop_change}")
        if self.check_every < 1:
            raise ValueError(f"tiger.ImplicitConfig: check_every must be >= 1, got {self.check_every}")
        if self.step_layout not in ("channels_last", "channels_first"):
            raise ValueError("tiger.ImplicitConfig: step_layout must be 'channels_last' or 'channels_first', "
                             f"got {self.step_layout!r}")
        from tiger.ops.featup import WINDOW_VARIANTS

        if self.attention_variant not in WINDOW_VARIANTS:
            raise ValueError(f"tiger.ImplicitConfig: attention_variant must be one of {WINDOW_VARIANTS}, "
                             f"got {self.attention_variant!r}")


def _tv(x: torch.Tensor) -> torch.Tensor:
    return (x[..., 1:, :] - x[..., :-1, :]).square().mean() + (x[..., :, 1:] - x[..., :, :-1]).square().mean()


def _fit_loss(cfg: "ImplicitConfig", out: torch.Tensor, target: torch.Tensor, outlier: nn.Module,
              hr: torch.Tensor, hr_mag: torch.Tensor, hr_blurred: Callable[[], torch.Tensor]) -> torch.Tensor:
    """FeatUp's fit loss, shared by the reference and the fast loop: the outlier-weighted
    reconstruction of the jittered views' coefficients ``target`` [B, k, fh, fw] by the
    downsampled output ``out`` [B, 1 + k, fh, fw] (magnitude first), the magnitude term, the
    total variation of the magnitude ``hr_mag`` and the blur pin of ``hr`` (``hr_blurred()``: its
    5-tap blur, computed only when the pin is on)."""
    magnitude, pred = out[:, :1], out[:, 1:]
    scales = torch.exp(outlier(target) + 0.1).clamp_min(1e-4)
    loss = ((pred - target).square() / (2 * scales**2) + scales.log()).mean()
    if cfg.mag_weight > 0:
        loss = loss + cfg.mag_weight * (magnitude - target.norm(dim=1, keepdim=True)).square().mean()
    if cfg.mag_tv_weight > 0:
        loss = loss + cfg.mag_tv_weight * _tv(hr_mag)
    if cfg.blur_pin > 0:
        loss = loss + cfg.blur_pin * (hr_blurred() - hr).square().mean()
    return loss


class ImplicitUpsampler:
    """Fit FeatUp's implicit upsampler to one image, then evaluate it at any resolution.

    Usage: ``up = ImplicitUpsampler.fit(image, featurizer)``; ``up(size) -> [D, H, W]``.
    ``image`` is [3, H, W] in [0, 1] at the featurizer's input size; ``featurizer`` maps images
    [B, 3, H, W] in [0, 1] to features [B, D, h, w].
    """

    def __init__(self, net: ImplicitNet, image: torch.Tensor, mean: torch.Tensor, basis: torch.Tensor,
                 history: list[float]) -> None:
        self.net, self.image, self.mean, self.basis, self.history = net, image, mean, basis, history
        # the fast fit's stopping checks [(step, 1 - mean cosine with the previous check's map)]
        # and how many jittered views it featurised (the reference featurises all of them)
        self.checks: list[tuple[int, float]] = []
        self.views_featurised = 0

    @classmethod
    def fit(cls, image: torch.Tensor, featurizer: Featurizer, config: ImplicitConfig | None = None,
            progress: bool = False) -> "ImplicitUpsampler":
        """Fit to ``image`` [3, H, W] in [0, 1]; deterministic for a given ``config.seed`` (the
        caller's random state is left untouched)."""
        cfg = config or ImplicitConfig()
        devices = [image.device] if image.device.type == "cuda" else []
        with torch.random.fork_rng(devices=devices):
            torch.manual_seed(cfg.seed)
            return cls._fit(image, featurizer, cfg, progress)

    @classmethod
    def _fit(cls, image: torch.Tensor, featurizer: Featurizer, cfg: ImplicitConfig,
             progress: bool) -> "ImplicitUpsampler":
        if image.dim() != 3 or image.shape[0] != 3:
            raise ValueError(f"tiger.ImplicitUpsampler: image must be [3, H, W], got {tuple(image.shape)}")
        dev = image.device
        gen = torch.Generator().manual_seed(cfg.seed)
        img = image.unsqueeze(0).float()
        h, w = img.shape[-2:]
        max_pad = int(round(cfg.max_pad * min(h, w) / 224))
        max_pad = min(max_pad, min(h, w) - 1)
        norm = (lambda f: F.layer_norm(f.permute(0, 2, 3, 1), f.shape[1:2]).permute(0, 3, 1, 2)) if cfg.channel_norm \
            else (lambda f: f)

        fast = cfg.method == "fast"
        with torch.no_grad():
            jitters = [sample_jitter(h, w, max_pad, cfg.max_zoom, cfg.use_flips, gen) for _ in range(cfg.n_views)]
            if fast:
                from .featup_fit import JitterTargets, fit_loop, jitter_params

                params = jitter_params(jitters, h, w, dev)
                lazy = JitterTargets(img, featurizer, params, cfg, norm)
                k = lazy.basis.shape[1]
            else:
                feats: list[torch.Tensor] = []
                for i in range(0, cfg.n_views, cfg.featurize_batch):
                    batch = torch.cat([j.apply(img) for j in jitters[i : i + cfg.featurize_batch]])
                    feats.append(norm(featurizer(batch).float()))
                views = torch.cat(feats)  # [N, D, fh, fw]
                del feats
                fh, fw = views.shape[-2:]
                mean, basis = _pca_basis(views[: cfg.pca_batch], cfg.proj_dim)  # on the views' device
                targets = _project(views, mean, basis)  # [N, k, fh, fw]
                k = basis.shape[1]
                del views
        net = ImplicitNet(k, cfg.n_freqs, gen, cfg.dropout, fused=cfg.fused_network).to(dev)
        down = AttentionDownsampler(k + 1, cfg.kernel_size, gen, cfg.dropout).to(dev)
        outlier = nn.Conv2d(k, 1, 1).to(dev)
        with torch.no_grad():
            outlier.weight.mul_(0.1)
            outlier.bias.mul_(0.1)
        if fast:
            history, checks = fit_loop(img, lazy, params, net, down, outlier, cfg, gen, progress)
            up = cls(net, img, lazy.mean, lazy.basis, history)
            up.checks, up.views_featurised = checks, lazy.featurised
            return up
        opt, steps = _fit_setup(net, down, outlier, cfg, progress)
        history: list[float] = []
        for _ in steps:
            hr = net(img)
            hr_mag = hr.norm(dim=1, keepdim=True)
            both = torch.cat([hr_mag, hr], dim=1)
            idx = torch.randint(0, cfg.n_views, (cfg.jitters_per_step,), generator=gen).tolist()
            target = targets[idx]
            jittered = torch.cat([jitters[i].apply(both) for i in idx])
            out = down(jittered, (fh, fw))
            loss = _fit_loss(cfg, out, target, outlier, hr, hr_mag,
                             lambda: gaussian_blur(hr, 5, 1.0, padding="reflect"))
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()
            history.append(float(loss.detach()))
        net.eval()
        up = cls(net, img, mean, basis, history)
        up.views_featurised = cfg.n_views
        return up

    @torch.no_grad()
    def __call__(self, size: tuple[int, int] | None = None, image: torch.Tensor | None = None) -> torch.Tensor:
        """Features [D, H, W] at ``size`` (default: the fitting size), from the fitted network on
        the image resized to that size (or on ``image`` [3, H, W] if given)."""
        img = self.image if image is None else image.unsqueeze(0).float()
        if size is not None and tuple(img.shape[-2:]) != tuple(size):
            img = F.interpolate(img, size=size, mode="bilinear", align_corners=False, antialias=True)
        coeffs = self.net(img)[0]  # [k, H, W]
        return torch.einsum("dk,khw->dhw", self.basis, coeffs) + self.mean.view(-1, 1, 1)


def _fit_setup(net: nn.Module, down: nn.Module, outlier: nn.Module, cfg: "ImplicitConfig",
               progress: bool, capturable: bool = False) -> tuple[torch.optim.Optimizer, Iterable[int]]:
    """What both fits start with: NAdam over the three modules' parameters (``capturable`` for a
    step captured in a CUDA graph), the step range (a progress bar when asked), and the network
    and downsampler in training mode (dropout)."""
    opt = torch.optim.NAdam([*net.parameters(), *down.parameters(), *outlier.parameters()], lr=cfg.lr,
                            capturable=capturable)
    steps: Iterable[int] = range(cfg.steps)
    if progress:
        from tiger.utils.progress import progress as progress_lines

        steps = progress_lines(steps, "FeatUp implicit", leave=False)
    net.train()
    down.train()
    return opt, steps


def _pca_basis(views: torch.Tensor, k: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Mean [D] and the top-k principal directions [D, k] of the feature vectors in views [N, D, h, w],
    float32 on the views' device (the PCA itself runs in float64 on the CPU)."""
    mean, comps, _ = fit_pca(views.permute(0, 2, 3, 1).reshape(-1, views.shape[1]), min(k, views.shape[1]))
    return mean.to(views.device, torch.float32), comps.to(views.device, torch.float32)


def _project(views: torch.Tensor, mean: torch.Tensor, basis: torch.Tensor) -> torch.Tensor:
    """PCA coefficients [N, k, h, w] of views [N, D, h, w] (mean [D], basis [D, k] on the views' device)."""
    return torch.einsum("ndhw,dk->nkhw", views - mean.view(1, -1, 1, 1), basis)


# ----------------------------------------------------------------------------- switch
UPSAMPLERS = ("implicit", "jbu", "bilinear")


def upsample_features(
    image: torch.Tensor,
    featurizer: Featurizer,
    size: tuple[int, int],
    mode: str = "implicit",
    *,
    jbu: JBUStack | None = None,
    implicit: ImplicitConfig | None = None,
    lowres: torch.Tensor | None = None,
    guidance_normalizer: Callable[[torch.Tensor], torch.Tensor] | None = None,
) -> torch.Tensor:
    """Pixel-level features [D, *size] of one image [3, H, W] (in [0, 1], at the featurizer's input size).

    ``mode`` is the quality/speed switch: 'implicit' (FeatUp implicit, per-image fit: the paper's
    choice, slow), 'jbu' (FeatUp JBU stack: fast; needs ``jbu``), 'bilinear' (baseline).
    ``lowres`` [D, h, w] reuses already computed backbone features.
    """
    if mode not in UPSAMPLERS:
        raise ValueError(f"tiger.upsample_features: mode must be one of {UPSAMPLERS}, got {mode!r}")
    if mode == "implicit":
        return ImplicitUpsampler.fit(image, featurizer, implicit)(size)
    lr = featurizer(image.unsqueeze(0)).float() if lowres is None else lowres.unsqueeze(0).float()
    if mode == "bilinear":
        return F.interpolate(lr, size=size, mode="bilinear", align_corners=False)[0]
    if jbu is None:
        raise ValueError("tiger.upsample_features: mode='jbu' needs a JBUStack (JBUStack.from_checkpoint(...))")
    guide = image.unsqueeze(0).float()
    if guidance_normalizer is not None:
        guide = guidance_normalizer(guide)
    h, w = lr.shape[-2:]
    guide = F.interpolate(guide, size=(16 * h, 16 * w), mode="bilinear", align_corners=False, antialias=True)
    p = next(jbu.parameters())
    with torch.no_grad():
        hr = jbu(lr.to(p.dtype), guide.to(p.dtype)).float()
    if tuple(hr.shape[-2:]) != tuple(size):
        hr = F.interpolate(hr, size=size, mode="bilinear", align_corners=False)
    return hr[0]
