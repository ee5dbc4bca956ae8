"""GroupNorm + SiLU: tiger's fused op against torch (``F.group_norm`` then ``F.silu``), NCHW and
channels-last, forward and forward+backward (to the input only: the guidance models are frozen),
with the error of each against a float64 evaluation of the formula; then whole models on CUDA:
the SD VAE encoder forward+backward to its input (4 x 3 x 512², and 256² as MVDream uses it) and
the InstructPix2Pix UNet forward (3 branches x 4 views, 64² latents), plain vs plain channels-last
vs fused norms + channels-last (``tiger.edit.guidance.fused_norms``). Also the fused models' other
op, a convolution's bias add: torch's broadcast add vs ``tiger.ops.channel_bias.channel_bias_add``.

Shapes: the SD VAE encoder's norms (4 x 128 x 512², 4 x 256 x 256², 4 x 512 x 128², 4 x 512 x 64²)
and the SD-1.5 UNet's at 12 x C x 64² ... 8² (on the CPU: N = 1 and 1/8 of the side, tiny models).

    python -m benchmarks.group_norm                         # CPU, small shapes
    python -m benchmarks.group_norm --device cuda --json out.json
"""
from __future__ import annotations

import argparse
import copy
import json
import time
from pathlib import Path

import torch
import torch.nn.functional as F

from benchmarks.common import cpu_time_ms, cuda_time_ms, print_table  # noqa: E402

from tiger.ops.channel_bias import channel_bias_add  # noqa: E402
from tiger.ops.group_norm import group_norm  # noqa: E402
from tiger.utils.dtypes import DTYPE_NAMES  # noqa: E402

VAE_SHAPES = [(4, 128, 512, 512), (4, 256, 256, 256), (4, 512, 128, 128), (4, 512, 64, 64)]
UNET_SHAPES = [(12, 320, 64, 64), (12, 640, 32, 32), (12, 1280, 16, 16), (12, 1280, 8, 8)]
GROUPS, EPS = 32, 1e-6


def reference(x, w, b):
    """silu(group_norm(x)) from the formula, float64 (the error yardstick)."""
    n, c, h, wd = x.shape
    xg = x.double().reshape(n, GROUPS, -1)
    mu = xg.mean(-1, keepdim=True)
    var = ((xg - mu) ** 2).mean(-1, keepdim=True)
    z = ((xg - mu) * torch.rsqrt(var + EPS)).reshape(n, c, h, wd) * w.double()[:, None, None] + b.double()[:, None, None]
    return z * torch.sigmoid(z)


def rel(a: torch.Tensor, ref: torch.Tensor) -> float:
    return float((a.detach().double() - ref).abs().max() / ref.abs().max().clamp_min(1e-30))


def op_rows(shapes, device: str, dtype: torch.dtype, iters: int) -> list[dict]:
    timer = cuda_time_ms if device == "cuda" else cpu_time_ms
    kw = dict(iters=iters, warmup=3) if device == "cuda" else dict(iters=iters, warmup=1)
    impls = {"torch": lambda x, w, b: F.silu(F.group_norm(x, GROUPS, w, b, EPS)),
             "tiger": lambda x, w, b: group_norm(x, GROUPS, w, b, EPS, silu=True)}
    rows = []
    for shape in shapes:
        g = torch.Generator(device=device).manual_seed(0)
        x0 = (0.5 + torch.randn(shape, device=device, generator=g)).to(dtype)
        w = (1 + 0.2 * torch.randn(shape[1], device=device, generator=g)).to(dtype)
        b = (0.2 * torch.randn(shape[1], device=device, generator=g)).to(dtype)
        gy = torch.randn(shape, device=device, generator=g).to(dtype)
        leaf = x0.double().requires_grad_()
        ref = reference(leaf, w, b)
        (ref_dx,) = torch.autograd.grad(ref, leaf, gy.double())
        ref = ref.detach()
        for layout in ("nchw", "channels_last"):
            x = x0.contiguous(memory_format=torch.channels_last) if layout != "nchw" else x0.contiguous()
            gyl = gy.contiguous(memory_format=torch.channels_last) if layout != "nchw" else gy
            row = {"shape": "x".join(map(str, shape)), "layout": layout}
            for name, fn in impls.items():
                xl = x.detach().requires_grad_()
                y = fn(xl, w, b)
                (dx,) = torch.autograd.grad(y, xl, gyl)
                row[f"{name}_out"] = "cl" if y.is_contiguous(memory_format=torch.channels_last) and not y.is_contiguous() else "nchw"
                row[f"{name}_fwd_ms"] = timer(lambda: fn(x, w, b), **kw)
                row[f"{name}_fwdbwd_ms"] = timer(lambda: torch.autograd.grad(fn(xl, w, b), xl, gyl), **kw)
                row[f"{name}_err_y"] = rel(y, ref)
                row[f"{name}_err_dx"] = rel(dx, ref_dx)
                del y, dx, xl
            row["fwd_speedup"] = row["torch_fwd_ms"] / row["tiger_fwd_ms"]
            row["fwdbwd_speedup"] = row["torch_fwdbwd_ms"] / row["tiger_fwdbwd_ms"]
            rows.append(row)
        del x0, gy, leaf, ref, ref_dx
        if device == "cuda":
            torch.cuda.empty_cache()
    return rows


def bias_rows(shapes, device: str, dtype: torch.dtype, iters: int) -> list[dict]:
    """A convolution's bias add: torch's broadcast ``x + b[:, None, None]`` vs tiger's
    ``channel_bias_add`` (both layouts), time and error against the float64 sum."""
    timer = cuda_time_ms if device == "cuda" else cpu_time_ms
    kw = dict(iters=iters, warmup=3) if device == "cuda" else dict(iters=iters, warmup=1)
    rows = []
    for shape in shapes:
        g = torch.Generator(device=device).manual_seed(1)
        x0 = torch.randn(shape, device=device, generator=g).to(dtype)
        b = torch.randn(shape[1], device=device, generator=g).to(dtype)
        ref = x0.double() + b.double()[None, :, None, None]
        for layout in ("nchw", "channels_last"):
            x = x0.contiguous(memory_format=torch.channels_last) if layout != "nchw" else x0
            row = {"shape": "x".join(map(str, shape)), "layout": layout}
            for name, fn in (("torch", lambda: x + b[None, :, None, None]), ("tiger", lambda: channel_bias_add(x, b))):
                row[f"{name}_ms"] = timer(fn, **kw)
                row[f"{name}_err"] = rel(fn(), ref)
            row["speedup"] = row["torch_ms"] / row["tiger_ms"]
            rows.append(row)
        del x0, ref
    return rows


def model_variants(model: torch.nn.Module):
    """(name, model): plain NCHW, plain channels-last, fused norms + channels-last."""
    from tiger.edit.guidance.fused_norms import apply_fused_norms

    cl = copy.deepcopy(model)
    torch.nn.Module.to(cl, memory_format=torch.channels_last)
    fused = copy.deepcopy(model)
    apply_fused_norms(fused, True)
    return [("plain", model), ("plain_cl", cl), ("fused_cl", fused)]


def vae_rows(device: str, dtype: torch.dtype, size: str, sides: list[int], iters: int) -> list[dict]:
    """SD VAE encoder forward + backward to the input (posterior mean), per variant; error of the
    input gradient against the float32 plain model's."""
    import diffusers

    from tiger.testing.random_models import sd_vae_config
    from tiger.edit.guidance.diffusers_models import freeze

    timer = cuda_time_ms if device == "cuda" else cpu_time_ms
    torch.manual_seed(0)
    with torch.device(device):
        base = diffusers.AutoencoderKL(**sd_vae_config(size))
    base.decoder = base.post_quant_conv = None
    ref_model = freeze(copy.deepcopy(base), device, torch.float32)
    model = freeze(base, device, dtype)
    rows = []
    for side in sides:
        g = torch.Generator(device=device).manual_seed(1)
        x = torch.rand(4, 3, side, side, device=device, generator=g) * 2 - 1
        xl = x.detach().requires_grad_()
        z = ref_model.encode(xl).latent_dist.mean
        gz = torch.randn(z.shape, device=device, generator=g)
        (ref_dx,) = torch.autograd.grad(z, xl, gz)
        del z, xl
        for name, m in model_variants(model):
            xin = x.to(dtype)
            if name != "plain":
                xin = xin.contiguous(memory_format=torch.channels_last)
            xin.requires_grad_()

            def step():
                zz = m.encode(xin).latent_dist.mean
                return torch.autograd.grad(zz, xin, gz.to(zz.dtype))[0]

            dx = step()
            row = {"model": f"vae {side}²", "variant": name, "fwd+bwd_ms": timer(step, iters=iters, warmup=2),
                   "err_dx_vs_fp32": rel(dx, ref_dx.double())}
            if device == "cuda":
                torch.cuda.reset_peak_memory_stats()
                step()
                row["peak_GiB"] = torch.cuda.max_memory_allocated() / 2 ** 30
            rows.append(row)
            del dx
        if device == "cuda":
            torch.cuda.empty_cache()
    base_ms = {r["model"]: r["fwd+bwd_ms"] for r in rows if r["variant"] == "plain"}
    for r in rows:
        r["speedup"] = base_ms[r["model"]] / r["fwd+bwd_ms"]
    del ref_model, model
    return rows


def unet_rows(device: str, dtype: torch.dtype, size: str, iters: int) -> list[dict]:
    """InstructPix2Pix UNet forward (no grad, as in the SDS step): 12 x 8 x 64² latents."""
    import diffusers

    from tiger.testing.random_models import ip2p_unet_config
    from tiger.edit.guidance.diffusers_models import freeze

    timer = cuda_time_ms if device == "cuda" else cpu_time_ms
    cfg = ip2p_unet_config(size)
    torch.manual_seed(0)
    with torch.device(device):
        unet = freeze(diffusers.UNet2DConditionModel(**cfg), device, dtype)
    side = 64 if size == "full" else 8
    g = torch.Generator(device=device).manual_seed(2)
    x = torch.randn(12, cfg["in_channels"], side, side, device=device, generator=g).to(dtype)
    t = torch.randint(20, 200, (12,), device=device, generator=g)
    emb = torch.randn(12, 77, cfg["cross_attention_dim"], device=device, generator=g).to(dtype)
    rows, outs = [], {}
    for name, m in model_variants(unet):
        xin = x if name == "plain" else x.contiguous(memory_format=torch.channels_last)
        with torch.no_grad():
            outs[name] = m(xin, t, encoder_hidden_states=emb).sample.float()
            ms = timer(lambda: m(xin, t, encoder_hidden_states=emb), iters=iters, warmup=2)
        rows.append({"model": "ip2p unet fwd", "variant": name, "fwd_ms": ms,
                     "rel_diff_vs_plain": rel(outs[name], outs["plain"].double())})
    for r in rows:
        r["speedup"] = rows[0]["fwd_ms"] / r["fwd_ms"]
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--device", default="cpu", choices=["cpu", "cuda"])
    ap.add_argument("--dtype", default="bf16", choices=sorted(DTYPE_NAMES), help="activations/model dtype (bf16)")
    ap.add_argument("--iters", type=int, default=None, help="timed repetitions (CUDA 20, CPU 3)")
    ap.add_argument("--skip-models", action="store_true", help="only the op table")
    ap.add_argument("--json", type=Path, default=None, help="write every row here")
    args = ap.parse_args()
    if args.device == "cuda" and not torch.cuda.is_available():
        ap.error("--device cuda: no CUDA device")
    cuda = args.device == "cuda"
    dtype = DTYPE_NAMES[args.dtype]
    iters = args.iters or (20 if cuda else 3)
    if cuda:
        torch.backends.cudnn.benchmark = True
        print(f"device: {torch.cuda.get_device_name()}, torch {torch.__version__}, {args.dtype}", flush=True)
        shapes = VAE_SHAPES + UNET_SHAPES
    else:
        dtype = torch.float32 if args.dtype == "bf16" else dtype  # CPU: bf16 GroupNorm is not what is measured
        shapes = [(1, c, max(8, h // 8), max(8, w // 8)) for _, c, h, w in VAE_SHAPES + UNET_SHAPES[:2]]
    t0 = time.perf_counter()
    out = {"op": op_rows(shapes, args.device, dtype, iters)}
    print_table(out["op"], f"== GroupNorm(32) + SiLU, {dtype}: torch vs tiger (ms; err = max|Δ| / max|ref| vs float64)")
    out["bias"] = bias_rows(shapes, args.device, dtype, iters)
    print_table(out["bias"], f"\n== conv bias add, {dtype}: torch's broadcast add vs tiger.channel_bias_add "
                             "(ms; err vs float64; both round once)")
    if not args.skip_models:
        size = "full" if cuda else "tiny"
        out["vae"] = vae_rows(args.device, dtype, size, [512, 256] if cuda else [32], iters)
        print_table(out["vae"], f"\n== SD VAE encoder ({size}) forward + backward to the input, 4 views")
        out["unet"] = unet_rows(args.device, dtype, size, iters)
        print_table(out["unet"], f"\n== InstructPix2Pix UNet ({size}) forward, 12 x 8 latents")
    print(f"\ntotal {time.perf_counter() - t0:.0f} s", flush=True)
    if args.json is not None:
        from tiger.utils.io import atomic_write

        with atomic_write(args.json, "w") as f:
            json.dump(out, f, indent=1)


if __name__ == "__main__":
    main()
