"""The CSD guidance step against its FLOP floor: what ``tiger edit`` runs per step (InstructPix2Pix
on 4 renders with the image condition encoded every step for fresh views, or cached for a camera
pool; MVDream on the same 4 views while its weight λ2 > 0, the first 75 % of the steps), with
the models as the loaders build them on CUDA (fused norms, channels-last, CUDA graph), random
weights in the real configurations.

Per variant it prints ms per guidance call and per CSD step (averaged over the λ schedule), the
FLOPs of each call (``torch.utils.flop_counter`` on an eager call: convolutions forward and
backward, matmuls, attention), the floor (FLOPs at the H100's measured 790 TFLOP/s bf16) and
the ratio to it, and the gradient's error on fixed noise and t (cosine similarity and relative
norm error) against the first variant and against a float32 reference of the same models.

Variants (one call measures all, each with a freshly captured CUDA graph; ``--variants`` picks):

- ``before``: the fused models' forwards before the folded adds (conv1's bias, the time
  embedding, conv2's bias and the shortcut as separate passes; the VAE attention's float32
  softmax upcast), reproduced here as a reference row (not in the default list);
- ``after``: the folded adds, diffusers' GEGLU and padded VAE downsampling (the package's
  default before :mod:`tiger.edit.guidance.model_kernels`);
- ``after+cudnn_benchmark``, ``after+flash_sdpa``: cuDNN's autotuning on; the UNets' attention
  without cuDNN's SDPA kernels (not in the default list);
- ``after+downsample_4x4``: the VAEs' stride-2 convolutions as unpadded-input 4x4 convolutions
  (``ModelKernels.vae_downsample_4x4``; 16/9 of those layers' FLOPs, the floor keeps the 3x3 count);
- ``after+geglu``: the UNets' one-pass GEGLU (``ModelKernels.fused_geglu``);
- ``after+fold_norm_bias``: conv1's bias and the time embedding added inside norm2 of every
  ResNet block (``ModelKernels.fold_norm_bias``);
- ``after+fp8``: only the UNets' transformer matmuls in FP8 with row-wise scales
  (``ModelKernels(matmul_precision="fp8")``, opt-in);
- ``default``: the exact-within-rounding kernels together (the package's default on CUDA);
- ``default-row_layer_norm``: the default with PyTorch's LayerNorm instead of the row kernel
  (``ModelKernels.row_layer_norm``);
- ``default-subpixel_upsample``: the default with diffusers' nearest upsampling + 3x3 convolution
  instead of the per-phase 2x2 convolutions (``ModelKernels.subpixel_upsample``);
- ``default-lean_attention``: the default with diffusers' SDPA attention processor
  (``ModelKernels.lean_attention``);
- ``default-block_backward``: the default with autograd's backward through the VAE's ResNet
  blocks (``ModelKernels.block_backward``);
- ``default-pad_conv_in``: the default with the first convolutions on their 3-8 input channels
  (``ModelKernels.pad_conv_in``);
- ``default-fused_transformer``: the default with diffusers' transformer-block forward (separate
  residual adds, q/k/v matmuls apart) instead of the fused blocks (``ModelKernels.fused_transformer``);
- ``default-carry_conv_bias``: the default with the VAE encoder's ``conv_in`` and downsampler biases
  added in passes of their own instead of by the next ResNet block (``ModelKernels.carry_conv_bias``);
- ``default-branch_prefix``: the default with InstructPix2Pix's instruction and image-only branches
  computed apart up to the first cross-attention instead of once (``ModelKernels.branch_prefix``);
- ``default-skip_concat``: the default with torch.cat for the UNets' up-block skip concatenations
  instead of their producers writing into the wide maps (``ModelKernels.skip_concat``);
- ``default-row_softmax``: the default with torch's softmax in the VAE attention instead of
  tiger's row kernel (``ModelKernels.row_softmax``);
- ``default+head40_attention``: the default with tiger's Hopper kernel instead of cuDNN's SDPA for
  InstructPix2Pix's head-dim-40 self-attentions (``ModelKernels.head40_attention``, opt-in);
- ``default+sequential``: the default kernels with MVDream run after InstructPix2Pix on one stream
  (every other variant runs it beside InstructPix2Pix on a side stream, ``CSDGuidance``'s default);
- ``default+fp8``, ``default+fp8_fast_accum``: and FP8 matmuls, plain or with
  ``torch._scaled_mm``'s fast accumulation.

FP8 rows need a GPU with FP8 tensor cores; elsewhere they are skipped with the reason. A variant
that fails prints its error and the run goes on. "FP8-eligible TFLOP" is the part of each call's
FLOPs in the layers FP8 converts (the ceiling of what FP8's 2x rate can save).

    python -m benchmarks.guidance_floor --device cuda              # full size, about 2 minutes
    python -m benchmarks.guidance_floor                            # CPU, tiny models (a smoke run)
"""
from __future__ import annotations

import argparse
import contextlib
import dataclasses
import json
import tempfile
import time
import types
from pathlib import Path
import torch

from benchmarks.common import count_flops, cpu_time_ms, cuda_time_ms, print_table
from benchmarks.guidance import H100_BF16_TFLOPS, build_models, ring, tokenizer
from tiger.edit.csd import CSDGuidance, CSDSchedule
from tiger.edit.guidance.base import ViewBatch
from tiger.edit.guidance.diffusers_models import _attention_probs_one_pass, freeze
from tiger.edit.guidance.fused_norms import _continuous_output_keep_layout, _resnet_forward_folded
from tiger.edit.guidance import model_kernels as mk
from tiger.edit.guidance.ip2p import InstructPix2PixGuidance
from tiger.edit.guidance.mvdream import MVDreamGuidance
from tiger.utils.dtypes import DTYPE_NAMES

PLAIN = mk.ModelKernels(fused_geglu=False, vae_downsample_4x4=False, fold_norm_bias=False, row_layer_norm=False,
                        subpixel_upsample=False, lean_attention=False, block_backward=False, pad_conv_in=False,
                        fused_transformer=False, carry_conv_bias=False, branch_prefix=False, stacked_time_bias=False,
                        cached_text_kv=False, skip_concat=False, row_softmax=False, head40_attention=False)
DEFAULT = mk.ModelKernels(fused_geglu=True, vae_downsample_4x4=True, fold_norm_bias=True, row_layer_norm=True,
                          subpixel_upsample=True, lean_attention=True, block_backward=True, pad_conv_in=True,
                          fused_transformer=True, carry_conv_bias=True, branch_prefix=True, stacked_time_bias=True,
                          cached_text_kv=True, skip_concat=True, row_softmax=True, head40_attention=False)


def _plain_and(**fields) -> mk.ModelKernels:
    return dataclasses.replace(PLAIN, **fields)


# name -> (kernels, folded adds, cuDNN autotuning, flash attention first)
VARIANTS = {
    "before": (PLAIN, False, False, False),
    "after": (PLAIN, True, False, False),
    "after+cudnn_benchmark": (PLAIN, True, True, False),
    "after+flash_sdpa": (PLAIN, True, False, True),
    "after+downsample_4x4": (_plain_and(vae_downsample_4x4=True), True, False, False),
    "after+geglu": (_plain_and(fused_geglu=True), True, False, False),
    "after+fold_norm_bias": (_plain_and(fold_norm_bias=True), True, False, False),
    "after+fp8": (_plain_and(matmul_precision="fp8"), True, False, False),
    "default": (DEFAULT, True, False, False),
    "default-row_layer_norm": (dataclasses.replace(DEFAULT, row_layer_norm=False), True, False, False),
    "default-subpixel_upsample": (dataclasses.replace(DEFAULT, subpixel_upsample=False), True, False, False),
    "default-lean_attention": (dataclasses.replace(DEFAULT, lean_attention=False), True, False, False),
    "default-block_backward": (dataclasses.replace(DEFAULT, block_backward=False), True, False, False),
    "default-pad_conv_in": (dataclasses.replace(DEFAULT, pad_conv_in=False), True, False, False),
    "default-fused_transformer": (dataclasses.replace(DEFAULT, fused_transformer=False), True, False, False),
    "default-carry_conv_bias": (dataclasses.replace(DEFAULT, carry_conv_bias=False), True, False, False),
    "default-branch_prefix": (dataclasses.replace(DEFAULT, branch_prefix=False), True, False, False),
    "default-stacked_time_bias": (dataclasses.replace(DEFAULT, stacked_time_bias=False), True, False, False),
    "default-cached_text_kv": (dataclasses.replace(DEFAULT, cached_text_kv=False), True, False, False),
    "default-skip_concat": (dataclasses.replace(DEFAULT, skip_concat=False), True, False, False),
    "default-row_softmax": (dataclasses.replace(DEFAULT, row_softmax=False), True, False, False),
    "default+head40_attention": (dataclasses.replace(DEFAULT, head40_attention=True), True, False, False),
    "default+sequential": (DEFAULT, True, False, False),
    "default+fp8": (dataclasses.replace(DEFAULT, matmul_precision="fp8"), True, False, False),
    "default+fp8_fast_accum": (dataclasses.replace(DEFAULT, matmul_precision="fp8", fp8_fast_accum=True),
                               True, False, False),
}
DEFAULT_VARIANTS = ("after", "after+downsample_4x4", "after+geglu", "after+fold_norm_bias", "after+fp8", "default",
                    "default-row_layer_norm", "default-subpixel_upsample", "default-lean_attention",
                    "default-block_backward", "default-pad_conv_in", "default-fused_transformer",
                    "default-carry_conv_bias", "default-branch_prefix", "default-stacked_time_bias",
                    "default-cached_text_kv", "default-skip_concat", "default-row_softmax",
                    "default+head40_attention", "default+fp8",
                    "default+fp8_fast_accum")
MV_FRACTION = CSDSchedule().mv_end  # MVDream runs while λ2 > 0: the first 75 % of the steps
FLOOR_TARGET = 1.6  # issue 30: the guidance step at most 1.6x its FLOP floor


def _separate_adds_resnet_forward(self, input_tensor, temb, *args, **kwargs):
    """The fused ResnetBlock2D forward before the fold: bias, time embedding and shortcut each
    one more pass over the map (the ``before`` row)."""
    h = self.conv1(self.norm1(input_tensor))
    if self.time_emb_proj is not None and temb is not None:
        h.add_(self.time_emb_proj(temb)[:, :, None, None])
    h = self.conv2(self.dropout(self.norm2(h)))
    shortcut = self.conv_shortcut(input_tensor) if self.conv_shortcut is not None else input_tensor
    return h.add_(shortcut)


def _separate_adds_transformer_output(self, hidden_states, residual, batch_size, height, width, inner_dim):
    """Transformer2DModel's channels-last output before the fold (projection, then the residual)."""
    if not self.use_linear_projection:
        hidden_states = hidden_states.reshape(batch_size, height, width, inner_dim).permute(0, 3, 1, 2)
        hidden_states = self.proj_out(hidden_states)
    else:
        hidden_states = self.proj_out(hidden_states)
        hidden_states = hidden_states.reshape(batch_size, height, width, inner_dim).permute(0, 3, 1, 2)
    return hidden_states.add_(residual)


def set_folded(models, folded: bool) -> int:
    """Switch the patched forwards of ``models`` (UNet and VAE) between the folded adds (the
    code's) and the separate passes (the ``before`` row); returns how many modules changed."""
    from diffusers.models.attention_processor import Attention
    from diffusers.models.resnet import ResnetBlock2D
    from diffusers.models.transformers.transformer_2d import Transformer2DModel

    changed = 0
    for model in (models.unet, models.vae):
        for m in model.modules():
            if type(m) is ResnetBlock2D and "forward" in m.__dict__:
                fn = _resnet_forward_folded if folded else _separate_adds_resnet_forward
                m.forward = types.MethodType(fn, m)
                changed += 1
            elif type(m) is Transformer2DModel and "_get_output_for_continuous_inputs" in m.__dict__:
                fn = _continuous_output_keep_layout if folded else _separate_adds_transformer_output
                m._get_output_for_continuous_inputs = types.MethodType(fn, m)
                changed += 1
            elif model is models.vae and isinstance(m, Attention):
                if folded:
                    m.get_attention_scores = types.MethodType(_attention_probs_one_pass, m)
                else:
                    m.__dict__.pop("get_attention_scores", None)
                changed += 1
    return changed


@contextlib.contextmanager
def attention_backends(flash_first: bool):
    """SDPA without cuDNN's kernels (flash, then memory-efficient, then math) when ``flash_first``."""
    if not flash_first:
        yield
        return
    from torch.nn.attention import SDPBackend, sdpa_kernel

    with sdpa_kernel([SDPBackend.FLASH_ATTENTION, SDPBackend.EFFICIENT_ATTENTION, SDPBackend.MATH]):
        yield


def cosine_rel(a: torch.Tensor, b: torch.Tensor) -> tuple[float, float]:
    """(cosine similarity, ‖a − b‖ / ‖b‖) in float64."""
    a, b = a.double().flatten(), b.double().flatten()
    return float(a @ b / (a.norm() * b.norm()).clamp_min(1e-300)), float((a - b).norm() / b.norm().clamp_min(1e-300))


def fixed_draws(ip: InstructPix2PixGuidance, mv: MVDreamGuidance, res: int, device: str) -> dict:
    """Fixed t, noise and VAE noise of both guidances (the gradient comparisons)."""
    gen = torch.Generator().manual_seed(7)
    size = ip.resolution(res, res)
    f_ip = 2 ** (len(ip.models.vae.config.block_out_channels) - 1)
    f_mv = 2 ** (len(mv.models.vae.config.block_out_channels) - 1)
    ip_shape = (4, ip.models.vae.config.latent_channels, size[0] // f_ip, size[1] // f_ip)
    mv_shape = (4, mv.models.vae.config.latent_channels, mv.image_size // f_mv, mv.image_size // f_mv)
    return {"ip2p": dict(t=torch.tensor([30, 80, 130, 190]), noise=torch.randn(ip_shape, generator=gen).to(device),
                         vae_noise=torch.randn(ip_shape, generator=gen).to(device)),
            "mvdream": dict(t=torch.tensor([120]), noise=torch.randn(mv_shape, generator=gen).to(device),
                            vae_noise=torch.randn(mv_shape, generator=gen).to(device))}


def default_cuda_guidances():
    """Full-size random InstructPix2Pix and MVDream models on CUDA (bf16, fused norms) with the
    ``default`` variant's kernels, and eager guidances on them: (ip_models, mv_models, ip, mv).
    The kernel profiles (``benchmarks.gpu.guidance_kernel_profile``, ``benchmarks.gpu.group_norm_ncu``)
    start here."""
    torch.manual_seed(0)
    ip_models, mv_models = build_models("full", "cuda", torch.bfloat16, tokenizer(Path(tempfile.mkdtemp())),
                                        fused_norms=True)
    kernels, folded = VARIANTS["default"][:2]
    set_folded(ip_models, folded)
    set_folded(mv_models, folded)
    ip, mv = make_guidances(ip_models, mv_models, graph=False, size="full", kernels=kernels)
    return ip_models, mv_models, ip, mv


def make_guidances(ip_models, mv_models, graph: bool, size: str, kernels: mk.ModelKernels = PLAIN):
    kw = {} if size == "full" else {"short_side": 64}
    ip = InstructPix2PixGuidance(ip_models, "turn the fox into a red panda", cuda_graph=graph, kernels=kernels, **kw)
    mv = MVDreamGuidance(mv_models, "a red panda", cuda_graph=graph, image_size=256 if size == "full" else 32,
                         kernels=kernels)
    return ip, mv


def fp8_eligible_flops(models, fn) -> float:
    """FLOPs of one ``fn()`` call in the layers FP8 converts (2·M·K·N each, by forward hooks)."""
    total = [0.0]

    def hook(module, inputs, output):
        k = module.in_channels if isinstance(module, torch.nn.Conv2d) else module.in_features
        total[0] += 2.0 * output.numel() * k

    handles = [parent._modules[name].register_forward_hook(hook)
               for parent, name, _, _ in mk._fp8_targets(models.unet)]
    try:
        fn()
    finally:
        for h in handles:
            h.remove()
    return total[0]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--size", default=None, help="tiny or full (default: full on CUDA, tiny on CPU)")
    ap.add_argument("--render", type=int, default=None, help="render side in pixels (default 512 full, 64 tiny)")
    ap.add_argument("--dtype", default=None, help="bf16 (CUDA default), fp16 or fp32 (CPU default)")
    ap.add_argument("--reps", type=int, default=10)
    ap.add_argument("--variants", default=",".join(DEFAULT_VARIANTS), help=f"comma list of {', '.join(VARIANTS)}")
    ap.add_argument("--no-reference", action="store_true", help="skip the float32 reference gradients")
    ap.add_argument("--out", type=Path, default=None, help="JSON file for the rows")
    args = ap.parse_args()
    t_start = time.perf_counter()
    cuda = args.device.startswith("cuda")
    size = args.size or ("full" if cuda else "tiny")
    res = args.render or (512 if size == "full" else 64)
    dtype = DTYPE_NAMES[args.dtype or ("bf16" if cuda else "fp32")]
    variants = args.variants.split(",")
    if any(v not in VARIANTS for v in variants):
        ap.error(f"--variants takes a comma list of {', '.join(VARIANTS)}, got '{args.variants}'")
    torch.manual_seed(0)
    tok = tokenizer(Path(tempfile.mkdtemp()))
    ip_models, mv_models = build_models(size, args.device, dtype, tok, fused_norms=True)  # as the loaders on CUDA
    renders = torch.rand(4, 3, res, res, device=args.device)
    originals = torch.rand(4, 3, res, res, device=args.device)
    cams = ring(4, res)

    def views(step: int, pooled: bool) -> ViewBatch:
        return ViewBatch(cameras=cams, originals=originals, view_ids=torch.arange(4) if pooled else None,
                         step=step, total_steps=4, object_center=torch.zeros(3))

    timer = ((lambda fn: cuda_time_ms(fn, iters=args.reps, warmup=3)) if cuda
             else (lambda fn: cpu_time_ms(fn, iters=max(1, args.reps // 5), warmup=1)))
    meta = {"device": torch.cuda.get_device_name() if cuda else "cpu", "torch": torch.__version__, "size": size,
            "render": res, "dtype": str(dtype).removeprefix("torch.")}

    # FLOPs of one eager call each (the variants change no FLOPs)
    ip_e, mv_e = make_guidances(ip_models, mv_models, graph=False, size=size)
    draws = fixed_draws(ip_e, mv_e, res, args.device)
    flops = {"ip2p_fresh": count_flops(lambda: ip_e.grad(renders, views(0, False)))}
    ip_e.grad(renders, views(0, True))  # fills the condition cache: the pooled call encodes no condition
    flops["ip2p_pooled"] = count_flops(lambda: ip_e.grad(renders, views(0, True)))
    flops["mvdream"] = count_flops(lambda: mv_e.grad(renders, views(0, False)))
    flops["csd_fresh"] = flops["ip2p_fresh"] + MV_FRACTION * flops["mvdream"]
    flops["csd_pooled"] = flops["ip2p_pooled"] + MV_FRACTION * flops["mvdream"]
    print("TFLOP per call:", json.dumps({k: round(v / 1e12, 3) for k, v in flops.items()}), flush=True)
    eligible = {"ip2p": fp8_eligible_flops(ip_models, lambda: ip_e.grad(renders, views(0, True))),
                "mvdream": fp8_eligible_flops(mv_models, lambda: mv_e.grad(renders, views(0, False)))}
    eligible["csd"] = eligible["ip2p"] + MV_FRACTION * eligible["mvdream"]
    print("FP8-eligible TFLOP per call (UNet transformer matmuls):",
          json.dumps({k: round(v / 1e12, 3) for k, v in eligible.items()}),
          f"= {eligible['csd'] / (H100_BF16_TFLOPS * 1e12) * 1e3:.2f} ms of the CSD floor", flush=True)
    ip_e = mv_e = None  # free the eager guidances

    rows: list[dict] = []
    grads: dict[str, dict[str, torch.Tensor]] = {}
    for variant in variants:
        kernels, folded, cudnn_benchmark, flash_first = VARIANTS[variant]
        if kernels.matmul_precision == "fp8":
            ok, why = mk.fp8_supported(args.device)
            if not ok or dtype != torch.bfloat16:
                print(f"{variant}: skipped ({why or 'FP8 matmuls need --dtype bf16'})", flush=True)
                continue
        try:
            with attention_backends(flash_first=flash_first):
                set_folded(ip_models, folded)
                set_folded(mv_models, folded)
                torch.backends.cudnn.benchmark = cudnn_benchmark
                ip_g, mv_g = make_guidances(ip_models, mv_models, graph=cuda, size=size, kernels=kernels)
                csd = CSDGuidance(ip_g, mv_g, concurrent=variant != "default+sequential")
                row = {"variant": variant}
                row["ip2p_fresh_ms"] = timer(lambda: ip_g.grad(renders, views(0, False)))
                row["ip2p_pooled_ms"] = timer(lambda: ip_g.grad(renders, views(0, True)))
                row["mvdream_ms"] = timer(lambda: mv_g.grad(renders, views(0, False)))
                both = {p: timer(lambda: csd.grad(renders, views(0, p == "pooled"))) for p in ("fresh", "pooled")}
                alone = {p: timer(lambda: csd.grad(renders, views(3, p == "pooled"))) for p in ("fresh", "pooled")}
                for p in ("fresh", "pooled"):
                    ms = MV_FRACTION * both[p] + (1 - MV_FRACTION) * alone[p]
                    floor_ms = flops[f"csd_{p}"] / (H100_BF16_TFLOPS * 1e12) * 1e3
                    row[f"csd_{p}_ms"] = ms
                    row[f"csd_{p}_tflop"] = flops[f"csd_{p}"] / 1e12
                    row[f"csd_{p}_floor_ms"] = floor_ms
                    row[f"csd_{p}_x_floor"] = ms / floor_ms
                ip_g = mv_g = csd = None  # the graphs' memory goes back to the pool
                ip_eager, mv_eager = make_guidances(ip_models, mv_models, graph=False, size=size, kernels=kernels)
                grads[variant] = {"ip2p": ip_eager.grad(renders, views(0, False), **draws["ip2p"])[0],
                                  "mvdream": mv_eager.grad(renders, views(0, False), **draws["mvdream"])[0]}
                ip_eager = mv_eager = None
        except Exception as exc:  # one failing variant must not lose the others' measurements
            print(f"{variant}: FAILED ({type(exc).__name__}: {exc})", flush=True)
            ip_g = mv_g = csd = ip_eager = mv_eager = None
            grads.pop(variant, None)
            if cuda:
                torch.cuda.synchronize()
                torch.cuda.empty_cache()
            continue
        first = rows[0]["variant"] if rows else None
        if first is not None:
            for name in ("ip2p", "mvdream"):
                cos, rel = cosine_rel(grads[variant][name], grads[first][name])
                row[f"{name}_cos_vs_{first}"], row[f"{name}_rel_vs_{first}"] = cos, rel
        rows.append(row)
        print(json.dumps(row), flush=True)
        if cuda:
            torch.cuda.empty_cache()
    torch.backends.cudnn.benchmark = False

    if not args.no_reference and dtype != torch.float32:  # the float32 reference of the same weights
        for models in (ip_models, mv_models):  # diffusers' layers back first: FP8 layers hold no float weights
            mk.apply_model_kernels(models.unet, models.vae, PLAIN)
            freeze(models.unet, dtype=torch.float32)
            freeze(models.vae, dtype=torch.float32)
        for models in (ip_models, mv_models):
            set_folded(models, True)
        ip_r, mv_r = make_guidances(ip_models, mv_models, graph=False, size=size, kernels=PLAIN)
        ref = {"ip2p": ip_r.grad(renders, views(0, False), **draws["ip2p"])[0],
               "mvdream": mv_r.grad(renders, views(0, False), **draws["mvdream"])[0]}
        for row in rows:
            for name in ("ip2p", "mvdream"):
                cos, rel = cosine_rel(grads[row["variant"]][name], ref[name])
                row[f"{name}_cos_vs_fp32"], row[f"{name}_rel_vs_fp32"] = cos, rel
    meta["wall_s"] = time.perf_counter() - t_start
    if not rows:
        raise SystemExit("no variant ran (see the errors above)")
    if args.out is not None:
        args.out.write_text(json.dumps({"meta": meta, "flops": flops, "fp8_eligible_flops": eligible, "rows": rows},
                                       indent=1))
    timing_cols = ["variant", "ip2p_fresh_ms", "ip2p_pooled_ms", "mvdream_ms", "csd_fresh_ms", "csd_fresh_floor_ms",
                   "csd_fresh_x_floor", "csd_pooled_ms", "csd_pooled_floor_ms", "csd_pooled_x_floor"]
    print_table([{c: r.get(c, "-") for c in timing_cols} for r in rows],
                title=f"CSD guidance step (ms; floor = FLOPs at {H100_BF16_TFLOPS:.0f} TFLOP/s), {meta}")
    error_cols = ["variant"] + [k for k in rows[0] if "_cos_" in k or "_rel_" in k]
    for r in rows[1:]:
        error_cols += [k for k in r if ("_cos_" in k or "_rel_" in k) and k not in error_cols]
    print_table([{c: r.get(c, "-") for c in error_cols} for r in rows],
                title="SDS gradient on fixed noise and t: cosine similarity and relative norm error")
    best = min(rows, key=lambda r: r["csd_fresh_ms"])
    print(f"default mode (fresh views): {best['csd_fresh_ms']:.1f} ms/step = {best['csd_fresh_x_floor']:.2f}x the "
          f"floor of {best['csd_fresh_floor_ms']:.1f} ms ({best['variant']}); target <= {FLOOR_TARGET}x: "
          f"{'met' if best['csd_fresh_x_floor'] <= FLOOR_TARGET else 'NOT met'}")


if __name__ == "__main__":
    main()
