"""The fast fit of FeatUp's implicit upsampler (the default of :meth:`ImplicitUpsampler.fit`).

Same model, parameters, initial weights, jitters and view picks as the reference loop in
:mod:`tiger.language.featup` (one CPU generator drives both), with the work rearranged:

* **Jitters as affine coordinates.** A FeatUp jitter (reflect-pad, bilinear zoom, crop, flip) is a
  separable bilinear resampling at affine coordinates (:func:`jitter_coords`); with
  ``align_corners=True`` and ``padding_mode="reflection"`` it reflects about the border pixel
  centres exactly as ``F.pad(mode="reflect")`` does, so the jittered copies of the backbone input
  (3000 of them, featurised once before the loop in batches) come from one ``grid_sample`` per batch.
* **The jittered downsampler as one op.** The reference unfolds each jittered, blurred 129-channel
  copy into [B, 129 x 29 x 29, cells] patches. Its attention logit is a linear map of each pixel,
  so it is computed on one channel before any jitter (the linear map commutes with blur and
  jitter, both linear and constant-preserving); the fit's copies are never materialised:
  ``tiger::jittered_window_attention`` (csrc/featup) reads each window's pixels through the
  bilinear jitter taps, takes the window softmax and the weighted sum, and its backward gathers
  the features' gradient per source pixel. The PyTorch composition it replaces,
  :func:`apply_jitters` then :func:`window_attention`, is kept as the reference it is tested
  against (tests/language/test_featup_fused.py).
* **Blur once, before the jitters** (the reference blurs each jittered copy): the blurred output
  is also the blur-pin regulariser's, so one blur serves both. With
  ``ImplicitConfig.step_layout="channels_last"`` (default) the network's output stays in its own
  layout up to the attention op (:func:`pre_attention`): ``tiger::magnitude_blur`` takes each
  pixel's magnitude and blurs (magnitude, features) in one op, ``tiger::masked_logit`` takes the
  attention logit of the dropped-out blurred map (the mask drawn channels first, as ``F.dropout``
  draws it), with no channels-first copy; ``"channels_first"`` is the PyTorch composition.
* **No host sync per step, one CUDA graph** (``ImplicitConfig.cuda_graph``): every step's view
  picks are drawn up front from the CPU generator in the reference's order, losses stay on the
  device, and on CUDA the step (forward, backward, NAdam with ``capturable=True``) is captured
  once and replayed (the dropout masks come from the device generator, which graphs advance per
  replay). bf16 autocast for the network and the backbone passes on CUDA
  (``ImplicitConfig.precision``).

Where the rearrangement is not exact (blur before zoom, the attention input's dropout mask shared
by overlapping windows and by the step's jitters, rounding), the fitted map is compared with the
reference fit by per-pixel cosine similarity (tests/language/test_featup_implicit.py,
benchmarks/featup_implicit.py).
"""
from __future__ import annotations

import contextlib
import logging
import math
from typing import TYPE_CHECKING, Callable, NamedTuple

import torch
import torch.nn.functional as F
from torch import nn

from tiger.utils.filters import gaussian_blur

logger = logging.getLogger(__name__)

if TYPE_CHECKING:  # imported at run time by featup.py, which imports this module lazily
    from .featup import AttentionDownsampler, Featurizer, ImplicitConfig, Jitter


def jitter_params(jitters: "list[Jitter]", h: int, w: int, device: torch.device) -> torch.Tensor:
    """[N, 7] float32 (pad, zoom, y, x, flip, zoomed rows, zoomed columns) of FeatUp jitters of an
    h x w image, for :func:`jitter_grid`. ``F.interpolate`` leaves a dimension whose zoomed size
    floor(size * zoom) equals its size untouched (scale 1), so the zoom is flagged per dimension."""
    rows = []
    for j in jitters:
        hp, wp = h + 2 * j.pad, w + 2 * j.pad
        zoomed = j.zoom > 1.0
        rows.append([j.pad, j.zoom, j.y, j.x, float(j.flip), float(zoomed and math.floor(hp * j.zoom) != hp),
                     float(zoomed and math.floor(wp * j.zoom) != wp)])
    return torch.tensor(rows, dtype=torch.float64).to(device, torch.float32)


def jitter_coords(params: torch.Tensor, h: int, w: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Source coordinates (pixels, before reflection) read by jitters ``params`` [N, 7] applied to
    an h x w image: rows [N, h] and columns [N, w] (a jitter is separable). Output pixel (y, x)
    reads where ``Jitter.apply`` reads: flip, crop offset, zoom as ``F.interpolate(scale_factor=zoom)``
    computes its source index, minus the pad. Computed in the dtype of ``params``."""
    pad, zoom, oy, ox, flip, zoom_y, zoom_x = (params[:, i].view(-1, 1) for i in range(7))
    dev, dt = params.device, params.dtype
    ys = torch.arange(h, device=dev, dtype=dt).view(1, -1)
    xs = torch.arange(w, device=dev, dtype=dt).view(1, -1)
    xs = torch.where(flip > 0.5, (w - 1) - xs, xs)

    def source(coord: torch.Tensor, zoomed: torch.Tensor) -> torch.Tensor:  # zoomed-padded -> image coordinate
        src = torch.where(zoomed > 0.5, ((coord + 0.5) / zoom - 0.5).clamp_min(0.0), coord)
        return src - pad

    return source(ys + oy, zoom_y), source(xs + ox, zoom_x)


def reflect_coords(coord: torch.Tensor, size: int) -> torch.Tensor:
    """``grid_sample``'s reflection (``padding_mode="reflection"``, ``align_corners=True``) of
    pixel coordinates about 0 and size - 1, clipped to [0, size - 1]."""
    if size <= 1:
        return torch.zeros_like(coord)
    span = float(size - 1)
    a = coord.abs()
    extra = torch.fmod(a, span)
    flips = torch.floor(a / span)
    out = torch.where(torch.remainder(flips, 2) == 0, extra, span - extra)
    return out.clamp(0.0, span)


def jitter_grid(params: torch.Tensor, h: int, w: int) -> torch.Tensor:
    """Sampling grids [N, h, w, 2] (normalised, ``align_corners=True``) of jitters ``params`` [N, 7]
    applied to an h x w image, from :func:`jitter_coords` (the reflection is ``grid_sample``'s)."""
    sy, sx = jitter_coords(params, h, w)  # [N, h], [N, w]
    gy = (2.0 * sy / max(h - 1, 1) - 1.0).view(-1, h, 1).expand(-1, h, w)
    gx = (2.0 * sx / max(w - 1, 1) - 1.0).view(-1, 1, w).expand(-1, h, w)
    return torch.stack([gx, gy], dim=-1)


def apply_jitters(x: torch.Tensor, grid: torch.Tensor) -> torch.Tensor:
    """Jittered copies [N, C, h, w] of ``x`` [1, C, h, w] (or [N, C, h, w]) on ``grid`` [N, h, w, 2]."""
    src = x.expand(grid.shape[0], -1, -1, -1) if x.shape[0] == 1 else x
    return F.grid_sample(src, grid.to(src.dtype), mode="bilinear", padding_mode="reflection", align_corners=True)


def window_geometry(h: int, w: int, size: tuple[int, int], kernel: int) -> tuple[int, int, int, int, int]:
    """(k, sh, sw, nh, nw): the reference downsampler's window size, strides and window counts."""
    fh, fw = size
    k = min(kernel, h, w)
    sh = max(1, (h - k) // max(fh - 1, 1))
    sw = max(1, (w - k) // max(fw - 1, 1))
    return k, sh, sw, (h - k) // sh + 1, (w - k) // sw + 1


def window_attention(down: "AttentionDownsampler", logit_map: torch.Tensor, x: torch.Tensor,
                     size: tuple[int, int], mask: torch.Tensor | None = None) -> torch.Tensor:
    """The attention downsampler's output [B, C, fh, fw] from its per-pixel logits ``logit_map``
    [B, 1, H, W] (the attention Linear applied to the blurred features) and the blurred features
    ``x`` [B, C, H, W]; the same windows, strides, logit mask and softmax as
    ``AttentionDownsampler.forward``, without its [B, fh, fw, k*k, C] patch tensor. ``mask``
    [B, fh, fw] replaces the logit mask drawn in training mode.

    Composed of PyTorch ops; with :func:`apply_jitters` it is the reference that the fused
    :func:`fused_window_attention` is tested against."""
    b, c, h, w = x.shape
    fh, fw = size
    k, sh, sw, nh, nw = window_geometry(h, w, size, down.kernel)
    logits = F.unfold(logit_map, k, stride=(sh, sw)).view(b, k * k, nh, nw)[:, :, :fh, :fw]
    if mask is not None:
        logits = logits * mask.view(b, 1, fh, fw)
    elif down.training and down.dropout > 0:
        logits = logits * (torch.rand(b, 1, fh, fw, device=x.device) > down.dropout)
    wk = down.w[:k, :k].reshape(1, -1, 1, 1)
    bk = down.b[:k, :k].reshape(1, -1, 1, 1)
    attn = F.softmax(logits * wk + bk, dim=1)  # [B, k*k, fh, fw]
    # windows a stride apart overlap; every ceil(k / stride)-th one does not
    gy_n, gx_n = math.ceil(k / sh), math.ceil(k / sw)
    out = x.new_zeros(b, c, fh, fw)
    for a in range(min(gy_n, fh)):
        for g in range(min(gx_n, fw)):
            sub = attn[:, :, a::gy_n, g::gx_n]
            gy, gx = sub.shape[-2:]
            sy, sx = gy_n * sh, gx_n * sw
            rh, rw = (gy - 1) * sy + k, (gx - 1) * sx + k
            weights = F.fold(sub.reshape(b, k * k, gy * gx), (rh, rw), k, stride=(sy, sx))  # [B, 1, rh, rw]
            region = x[:, :, a * sh : a * sh + rh, g * sw : g * sw + rw]
            out[:, :, a::gy_n, g::gx_n] = F.avg_pool2d(region * weights.to(region.dtype), k, stride=(sy, sx),
                                                       divisor_override=1)
    return out


def _autocast(device: torch.device, precision: str):
    # no weight-cast cache: every weight is cast once per step anyway, and a cache kept across
    # a CUDA-graph capture would hold casts of the capture's (not the replays') weights
    if precision == "bf16" and device.type == "cuda":
        return torch.autocast("cuda", dtype=torch.bfloat16, cache_enabled=False)
    return contextlib.nullcontext()


def fused_window_attention(down: "AttentionDownsampler", logit_map: torch.Tensor, features: torch.Tensor,
                           coord_y: torch.Tensor, coord_x: torch.Tensor, size: tuple[int, int],
                           mask: torch.Tensor, variant: str = "baseline") -> torch.Tensor:
    """``window_attention(down, *apply_jitters(cat([logit_map, x]), grid).split([1, C], 1), size, mask)``
    in one op (``tiger::jittered_window_attention``), without the jittered copies; x is
    ``features`` channels first.

    ``logit_map`` [H, W], ``features`` [H, W, C] channels last (float32/float64; read in place
    when contiguous); ``coord_y`` [J, H] and ``coord_x`` [J, W] the jitters' reflected source
    coordinates (:func:`jitter_coords`, :func:`reflect_coords`); ``mask`` [J, fh, fw] the logit
    mask. ``variant``: the op's CUDA kernels (:data:`tiger.ops.featup.WINDOW_VARIANTS`). Returns
    [J, C, fh, fw] (a view of the op's channels-last output).
    """
    from tiger.ops.featup import jittered_window_attention

    h, w = features.shape[:2]
    k, sh, sw, _, _ = window_geometry(h, w, size, down.kernel)
    dt = features.dtype
    out, _ = jittered_window_attention(features.contiguous(), logit_map.to(dt), coord_y.to(dt), coord_x.to(dt),
                                       down.w[:k, :k].to(dt), down.b[:k, :k].to(dt), mask.to(dt), (sh, sw),
                                       variant)
    return out.permute(0, 3, 1, 2)


# FeatUp blurs the attention's input with 5 taps (radius 2) of a sigma-1 Gaussian, reflect padded
BLUR_RADIUS, BLUR_SIGMA = 2, 1.0


class PreAttention(NamedTuple):
    """The step's tensors between the network and the attention op (:func:`pre_attention`)."""

    features: torch.Tensor  # [h, w, 1 + C] blurred (magnitude, features), channels last, float32/64
    logit_map: torch.Tensor  # [h, w] the attention logit of the dropped-out blurred map
    hr: torch.Tensor  # the network's output as the blur pin reads it ([h, w, C] or [1, C, h, w])
    hr_mag: torch.Tensor  # its per-pixel magnitude ([h, w] or [1, 1, h, w])
    hr_blurred: Callable[[], torch.Tensor]  # hr's blur, in hr's layout


def pre_attention(hr: torch.Tensor, down: "AttentionDownsampler", layout: str) -> PreAttention:
    """The step's block from the network's output ``hr`` [1, C, h, w] (any dtype; in the fit a
    view of the network's channels-last [1, h, w, C]) to the attention op's inputs: each pixel's
    magnitude, the reflect blur of (magnitude, features), the attention's input dropout and its
    per-pixel logit (``down.attention[1]``, a linear map of the 1 + C channels).

    ``layout="channels_last"``: ``tiger::magnitude_blur`` on the network's layout (read in its
    dtype, accumulated in float32) and ``tiger::masked_logit`` with the dropout mask drawn
    channels first, as ``F.dropout`` draws it for [1, 1 + C, h, w]. ``"channels_first"``: the
    PyTorch composition (float32 copy, norm, cat, depthwise blur, ``F.dropout``, 1x1 conv, and
    the channels-last copy the attention op reads). The blurred map and the logit map are
    float32 (float64 for a float64 ``hr``).
    """
    lin = down.attention[1]
    p = down.dropout
    if layout == "channels_last":
        from tiger.ops.featup import magnitude_blur, masked_logit

        hr_hwc = hr[0].permute(1, 2, 0)  # [h, w, C]: no copy when hr is a channels-last view
        blurred, hr_mag = magnitude_blur(hr_hwc, BLUR_RADIUS, BLUR_SIGMA)  # [h, w, 1 + C], [h, w]
        keep = None
        if p > 0:  # F.dropout's draws for the channels-first map (bernoulli in its element order)
            keep = torch.empty(blurred.shape[-1], *blurred.shape[:2], dtype=torch.bool,
                               device=blurred.device).bernoulli_(1 - p)
        keep_scale = 1.0 / (1.0 - p) if p < 1 else 0.0  # F.dropout(p=1) zeroes everything
        logit_map = masked_logit(blurred, lin.weight.view(-1), lin.bias, keep, keep_scale)
        return PreAttention(blurred, logit_map, hr_hwc, hr_mag, lambda: blurred[..., 1:])
    if layout != "channels_first":
        raise ValueError(f"tiger: pre_attention layout must be 'channels_last' or 'channels_first', got {layout!r}")
    hr = hr.to(torch.promote_types(hr.dtype, torch.float32)).contiguous()
    hr_mag = hr.norm(dim=1, keepdim=True)
    blurred = gaussian_blur(torch.cat([hr_mag, hr], dim=1), 2 * BLUR_RADIUS + 1, BLUR_SIGMA, padding="reflect")
    logit_in = F.dropout(blurred, p, training=True) if p > 0 else blurred
    logit_map = F.conv2d(logit_in, lin.weight.view(1, -1, 1, 1), lin.bias)  # [1, 1, h, w]
    features = blurred[0].permute(1, 2, 0).contiguous()
    return PreAttention(features, logit_map[0, 0], hr, hr_mag, lambda: blurred[:, 1:])


def featurize_jitters(img: torch.Tensor, featurizer: "Featurizer", params: torch.Tensor, batch: int,
                      precision: str, norm) -> torch.Tensor:
    """Backbone features [N, D, fh, fw] (float32) of the N jittered copies of ``img`` [1, 3, h, w].
    For ``precision="bf16"`` on CUDA a featurizer that can run its weights in bf16
    (``vision_in``, e.g. :class:`~tiger.language.maskclip.MaskCLIP`) does so; others run under
    bf16 autocast."""
    h, w = img.shape[-2:]
    feats = []
    bf16 = precision == "bf16" and img.device.type == "cuda"
    if bf16 and hasattr(featurizer, "vision_in"):
        featurizer, precision = featurizer.vision_in(torch.bfloat16), "fp32"  # no autocast casts
    with torch.no_grad(), _autocast(img.device, precision):
        for i in range(0, params.shape[0], batch):
            views = apply_jitters(img, jitter_grid(params[i : i + batch], h, w))
            feats.append(norm(featurizer(views).float()))
    return torch.cat(feats)


class JitterTargets:
    """PCA coefficients of a fit's N jittered views, featurised when a step first picks them.

    The PCA basis comes from the first ``cfg.pca_batch`` views, featurised at construction (as the
    reference does); ``buffer`` [N, k, fh, fw] (float32, fixed storage, so a CUDA graph may read
    it) holds the coefficients of the views featurised so far. ``img`` [1, 3, h, w]; ``params``
    [N, 7] the views' jitters (:func:`jitter_params`)."""

    def __init__(self, img: torch.Tensor, featurizer: "Featurizer", params: torch.Tensor, cfg: "ImplicitConfig",
                 norm) -> None:
        from .featup import _pca_basis, _project

        self._project = _project
        self.img, self.featurizer, self.params, self.cfg, self.norm = img, featurizer, params, cfg, norm
        n = params.shape[0]
        first = featurize_jitters(img, featurizer, params[: cfg.pca_batch], cfg.featurize_batch, cfg.precision, norm)
        self.mean, self.basis = _pca_basis(first, cfg.proj_dim)
        self.buffer = first.new_empty(n, self.basis.shape[1], *first.shape[-2:])
        self.buffer[: first.shape[0]] = _project(first, self.mean, self.basis)
        self.ready = torch.zeros(n, dtype=torch.bool)
        self.ready[: first.shape[0]] = True

    @property
    def featurised(self) -> int:
        return int(self.ready.sum())

    @torch.no_grad()
    def ensure(self, picks: torch.Tensor) -> None:
        """Featurise the views among ``picks`` (CPU long tensor, any shape) not featurised yet."""
        need = picks.flatten().unique()
        need = need[~self.ready[need]]
        if need.numel() == 0:
            return
        rows = need.to(self.params.device)
        feats = featurize_jitters(self.img, self.featurizer, self.params[rows], self.cfg.featurize_batch,
                                  self.cfg.precision, self.norm)
        self.buffer[rows] = self._project(feats, self.mean, self.basis)
        self.ready[need] = True


@torch.no_grad()
def fitted_directions(net: nn.Module, img: torch.Tensor, targets: JitterTargets, precision: str) -> torch.Tensor:
    """The fitted map at the fitting resolution, projected back to the feature space and normalised
    per pixel: [D, h * w] (what the fit's result is compared by: per-pixel cosine similarity).
    Evaluated without dropout; the network's training mode is restored."""
    was_training = net.training
    net.eval()
    with _autocast(img.device, precision):
        coeffs = net.forward_pixels(img)[0].float()  # [k, h, w]
    net.train(was_training)
    feats = targets.basis @ coeffs.reshape(coeffs.shape[0], -1) + targets.mean.view(-1, 1)
    return F.normalize(feats, dim=0)


def fit_loop(img: torch.Tensor, targets: JitterTargets, params: torch.Tensor, net: nn.Module,
             down: "AttentionDownsampler", outlier: nn.Conv2d, cfg: "ImplicitConfig", gen: torch.Generator,
             progress: bool) -> tuple[list[float], list[tuple[int, float]]]:
    """Run the fit's NAdam steps in place on (net, down, outlier), at most ``cfg.steps``, stopping
    once the fitted map settles (``cfg.stop_change``; see ``ImplicitConfig``). Returns the losses
    and the stopping checks [(step, 1 - mean per-pixel cosine with the previous check's map)].

    ``img`` [1, 3, h, w]; ``targets`` the PCA coefficients of the jittered views whose jitters are
    ``params`` [N, 7], featurised as steps pick them; ``gen`` draws each step's view picks (as the
    reference does: all steps' picks are drawn up front, in the reference's order). On CUDA with
    ``cfg.cuda_graph`` the step (forward, backward, NAdam) is captured once in a CUDA graph and
    replayed; if the capture fails the loop goes on eagerly.
    """
    from .featup import _fit_setup

    dev = img.device
    h, w = img.shape[-2:]
    graph = dev.type == "cuda" and cfg.cuda_graph
    opt, steps = _fit_setup(net, down, outlier, cfg, progress, capturable=graph)
    steps = iter(steps)
    picks_host = torch.stack([torch.randint(0, cfg.n_views, (cfg.jitters_per_step,), generator=gen)
                              for _ in range(cfg.steps)]) if cfg.steps else None
    picks = picks_host.to(dev) if cfg.steps else None
    buffer = targets.buffer
    sy, sx = jitter_coords(params.double(), h, w)
    coord_y, coord_x = reflect_coords(sy, h).float(), reflect_coords(sx, w).float()
    losses = torch.empty(cfg.steps, device=dev)
    idx = torch.zeros(cfg.jitters_per_step, dtype=torch.long, device=dev)
    network = torch.compile(net.forward_pixels, dynamic=False) if cfg.compile_network else net.forward_pixels

    def step() -> torch.Tensor:
        loss = _step_loss(img, buffer, idx, coord_y, coord_x, network, down, outlier, cfg)
        loss.backward()
        opt.step()
        return loss.detach()

    def eager(i: int) -> None:
        idx.copy_(picks[i])
        opt.zero_grad(set_to_none=True)
        losses[i] = step()

    cuda_graph, static_loss, captured = None, None, False

    def run(start: int, end: int) -> None:
        nonlocal cuda_graph, static_loss, captured
        i = start
        if graph and not captured:
            captured = True  # one try
            warm = min(3, end - i)  # real steps, run on a side stream as graph capture requires
            side = torch.cuda.Stream(dev)
            side.wait_stream(torch.cuda.current_stream(dev))
            with torch.cuda.stream(side):
                for _ in range(warm):
                    next(steps)
                    eager(i)
                    i += 1
            torch.cuda.current_stream(dev).wait_stream(side)
            try:
                cuda_graph = torch.cuda.CUDAGraph()
                opt.zero_grad(set_to_none=True)
                # thread_local: another thread may drive its own stream meanwhile (the features
                # stage runs SAM beside the fit, tiger.utils.streams.run_beside)
                with torch.cuda.graph(cuda_graph, capture_error_mode="thread_local"):
                    static_loss = step()
            except RuntimeError as exc:  # capture is best effort: the eager loop is the same step
                logger.warning("FeatUp fit: CUDA graph capture failed (%s); running the steps eagerly", exc)
                cuda_graph = None
        for i in range(i, end):
            next(steps)
            if cuda_graph is not None:
                idx.copy_(picks[i])
                cuda_graph.replay()
                losses[i] = static_loss
            else:
                eager(i)

    stopping = cfg.stop_change > 0
    chunk = cfg.check_every if stopping else max(cfg.steps, 1)
    checks: list[tuple[int, float]] = []
    previous = None
    done = 0
    while done < cfg.steps:
        end = min(done + chunk, cfg.steps)
        targets.ensure(picks_host[done:end])
        run(done, end)
        done = end
        if stopping and done < cfg.steps and done + chunk >= cfg.min_steps:
            current = fitted_directions(net, img, targets, cfg.precision)
            if previous is not None:
                change = 1.0 - float((current * previous).sum(0).mean())
                checks.append((done, change))
                if done >= cfg.min_steps and change < cfg.stop_change:
                    logger.debug("FeatUp fit: map settled after %d steps (change %.2e)", done, change)
                    break
            previous = current
    if hasattr(steps, "close"):
        steps.close()
    else:
        for _ in steps:  # closes the progress display
            pass
    net.eval()
    return losses[:done].tolist(), checks


def _step_loss(img: torch.Tensor, targets: torch.Tensor, idx: torch.Tensor, coord_y: torch.Tensor,
               coord_x: torch.Tensor, network, down: "AttentionDownsampler", outlier: nn.Conv2d,
               cfg: "ImplicitConfig") -> torch.Tensor:
    """One step's loss (the reference loop's terms) on the views ``idx`` [J] (device tensor);
    ``network`` is the implicit network's ``forward_pixels`` (or its compiled form); the block
    before the attention op in ``cfg.step_layout`` (:func:`pre_attention`)."""
    from .featup import _fit_loss

    dev = img.device
    fh, fw = targets.shape[-2:]
    with _autocast(dev, cfg.precision):
        hr = network(img)
    pre = pre_attention(hr, down, cfg.step_layout)
    n = idx.shape[0]
    if down.dropout > 0:
        mask = (torch.rand(n, fh, fw, device=dev) > down.dropout).float()
    else:
        mask = torch.ones(n, fh, fw, device=dev)
    out = fused_window_attention(down, pre.logit_map, pre.features, coord_y[idx], coord_x[idx], (fh, fw), mask,
                                 cfg.attention_variant)
    return _fit_loss(cfg, out, targets[idx], outlier, pre.hr, pre.hr_mag, pre.hr_blurred)
