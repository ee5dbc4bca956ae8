"""Diffusion guidance: time of one 4-view SDS gradient (InstructPix2Pix, MVDream), split into VAE
encode, UNet passes and VAE backward; FLOPs (torch.utils.flop_counter) and their ratio to the H100's
bf16 matrix throughput; peak memory with both models loaded.

Models are randomly initialised in the real configurations (``--size full``: SD-1.5 InstructPix2Pix
UNet with 8 input channels + SD VAE at 512x512; SD-2.1-base MVDream UNet with the camera embedding
and multi-view attention + its VAE at 256x256; the cost of the real weights), or tiny (``--size
tiny``, CPU). One run measures every variant: dtype (bf16, fp16), channels-last, cuDNN autotuning,
and the execution mode: ``eager``, ``graph`` (the whole step replayed as one CUDA graph),
``compile_vae`` (torch.compile on the VAE encoder, then the CUDA graph), ``compile`` (torch.compile
on the UNet and the VAE encoder, then the CUDA graph).

    python -m benchmarks.guidance                                   # CPU, tiny models
    python -m benchmarks.guidance --device cuda --size full --out results.json
"""
from __future__ import annotations

import argparse
import gc
import json
import math
import tempfile
import time
from pathlib import Path
from typing import Optional

import torch

from benchmarks.common import count_flops, cpu_time_ms, cuda_time_ms, print_table  # noqa: E402

from tiger.edit.guidance.base import ViewBatch  # noqa: E402
from tiger.edit.guidance.fused_norms import apply_fused_norms  # noqa: E402
from tiger.edit.guidance.ip2p import InstructPix2PixGuidance, IP2PModels  # noqa: E402
from tiger.edit.guidance.ldm_checkpoint import unet_config_from_ldm, vae_config_from_ldm  # noqa: E402
from tiger.edit.guidance.mvdream import MVDreamGuidance, MVDreamModels  # noqa: E402
from tiger.edit.guidance.mvdream_attention import install_multiview_attention  # noqa: E402
from tiger.testing.random_models import ip2p_unet_config, mvdream_ldm_config, sd_vae_config  # noqa: E402
from tiger.edit.guidance.diffusers_models import PromptEncoder, encode_latents, freeze, resize  # noqa: E402
from tiger.edit.guidance.noise_schedule import NoiseSchedule  # noqa: E402
from tiger.testing.random_models import write_byte_level_clip_tokenizer  # noqa: E402
from tiger.render import Camera  # noqa: E402
from tiger.utils.dtypes import DTYPE_NAMES  # noqa: E402

H100_BF16_TFLOPS = 790.0  # measured 8192^3 bf16 matmul on the device (KINDS.md)


def tokenizer(folder: Path):
    import transformers

    write_byte_level_clip_tokenizer(folder)
    return transformers.CLIPTokenizer(str(folder / "vocab.json"), str(folder / "merges.txt"), model_max_length=77,
                                      pad_token="!")


def build_models(size: str, device: str, dtype: torch.dtype, tok,
                 fused_norms: Optional[bool] = False) -> tuple[IP2PModels, MVDreamModels]:
    """Both guidances' models, random weights, built directly on ``device``; ``fused_norms`` as
    for ``load_ip2p`` / ``load_mvdream`` (None: their default, VAE and UNet fused on CUDA)."""
    import diffusers
    import transformers

    schedule = NoiseSchedule.from_betas(0.00085, 0.012).to(device)
    vocab = 49408 if size == "full" else len(tok)
    with torch.device(device):
        unet = diffusers.UNet2DConditionModel(**ip2p_unet_config(size))
        vae = diffusers.AutoencoderKL(**sd_vae_config(size))
        w, layers, heads = (768, 12, 12) if size == "full" else (32, 2, 2)
        text = transformers.CLIPTextModel(transformers.CLIPTextConfig(
            vocab_size=vocab, hidden_size=w, intermediate_size=4 * w, num_hidden_layers=layers,
            num_attention_heads=heads, max_position_embeddings=77))
    vae.decoder = vae.post_quant_conv = None
    ip2p = IP2PModels(freeze(unet, device, dtype, fused_norms), freeze(vae, device, dtype, fused_norms),
                      PromptEncoder(tok, freeze(text, device), device, dtype), schedule)
    ldm = mvdream_ldm_config(size)
    with torch.device(device):
        unet = diffusers.UNet2DConditionModel(**unet_config_from_ldm(ldm))
        vae = diffusers.AutoencoderKL(**vae_config_from_ldm(ldm))
        w, layers = (1024, 23) if size == "full" else (64, 2)
        text = transformers.CLIPTextModel(transformers.CLIPTextConfig(
            vocab_size=vocab, hidden_size=w, intermediate_size=4 * w, num_hidden_layers=layers,
            num_attention_heads=max(1, w // 64), max_position_embeddings=77, hidden_act="gelu"))
    install_multiview_attention(unet, 4)
    vae.decoder = vae.post_quant_conv = None
    mv = MVDreamModels(freeze(unet, device, dtype, fused_norms), freeze(vae, device, dtype, fused_norms),
                       PromptEncoder(tok, freeze(text, device), device, dtype), schedule)
    return ip2p, mv


def ring(n: int, res: int) -> list[Camera]:
    cams = []
    for k in range(n):
        a = 2 * math.pi * k / n
        c2w = torch.eye(4, dtype=torch.float64)
        pos = torch.tensor([3 * math.sin(a), -3 * math.cos(a), 1.0], dtype=torch.float64)
        fwd = -pos / pos.norm()
        right = torch.linalg.cross(fwd, torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64))
        right /= right.norm()
        c2w[:3, 0], c2w[:3, 1], c2w[:3, 2], c2w[:3, 3] = right, torch.linalg.cross(fwd, right), fwd, pos
        K = torch.tensor([[res, 0, res / 2], [0, res, res / 2], [0, 0, 1]], dtype=torch.float64)
        cams.append(Camera(torch.linalg.inv(c2w), K, res, res))
    return cams


FUSED_LEVELS = ("off", "vae", "all")  # tiger's fused GroupNorm+SiLU in: neither model, the VAEs, both


def set_format(models, channels_last: bool, fused: str) -> None:
    """UNet and VAE memory format; a model with fused norms stays channels-last (their layout)."""
    fmt = torch.channels_last if channels_last else torch.contiguous_format
    models.unet.to(memory_format=torch.channels_last if fused == "all" else fmt)
    models.vae.to(memory_format=torch.channels_last if fused != "off" else fmt)


def split_ms(guidance, renders: torch.Tensor, views: ViewBatch, cuda: bool, reps: int) -> dict[str, float]:
    """Median ms of the three pieces of one eager step: VAE encode, UNet passes (+ CFG), VAE backward."""
    m = guidance.models
    v, _, h, w = renders.shape
    is_ip2p = isinstance(guidance, InstructPix2PixGuidance)
    size = guidance.resolution(h, w) if is_ip2p else (guidance.image_size, guidance.image_size)
    f = 2 ** (len(m.vae.config.block_out_channels) - 1)
    lat = (v, m.vae.config.latent_channels, size[0] // f, size[1] // f)
    dev = renders.device
    noise, vae_noise = torch.randn(lat, device=dev), torch.randn(lat, device=dev)
    if is_ip2p:
        extra = guidance.condition_latents(views.originals, size, views.view_ids)
        t = torch.full((v,), 100, device=dev, dtype=torch.long)
    else:
        extra = guidance.camera_conditions(views)
        t = torch.full((1,), 100, device=dev, dtype=torch.long)
    times: dict[str, list[float]] = {"encode_ms": [], "unet_ms": [], "backward_ms": []}
    clock = (lambda: torch.cuda.Event(enable_timing=True)) if cuda else None
    for i in range(reps + 2):
        if cuda:
            ev = [clock() for _ in range(4)]
            torch.cuda.synchronize()
            ev[0].record()
        else:
            ts = [time.perf_counter()]
        with torch.enable_grad():
            x = renders.detach().requires_grad_(True)
            z = encode_latents(m.vae, resize(x, size), vae_noise)
            ev[1].record() if cuda else ts.append(time.perf_counter())
            g = guidance.latent_grad(z.detach(), extra, t, noise)
            ev[2].record() if cuda else ts.append(time.perf_counter())
            torch.autograd.grad(z, x, grad_outputs=g.to(z.dtype))
            ev[3].record() if cuda else ts.append(time.perf_counter())
        if cuda:
            torch.cuda.synchronize()
            d = [ev[k].elapsed_time(ev[k + 1]) for k in range(3)]
        else:
            d = [1e3 * (ts[k + 1] - ts[k]) for k in range(3)]
        if i >= 2:
            for key, val in zip(times, d):
                times[key].append(val)
    return {k: sorted(v)[len(v) // 2] for k, v in times.items()}


def make_guidances(ip2p_models, mv_models, graph: bool, size: str):
    kw = {} if size == "full" else {"short_side": 64}
    ip = InstructPix2PixGuidance(ip2p_models, "turn the fox into a red panda", cuda_graph=graph, **kw)
    mv = MVDreamGuidance(mv_models, "a red panda", cuda_graph=graph, image_size=256 if size == "full" else 32)
    return ip, mv


def profile_table(fn, path: Path, rows: int = 30) -> None:
    from torch.profiler import ProfilerActivity, profile

    fn()
    torch.cuda.synchronize()
    with profile(activities=[ProfilerActivity.CUDA, ProfilerActivity.CPU], record_shapes=True) as prof:
        fn()
        torch.cuda.synchronize()
    path.write_text(prof.key_averages().table(sort_by="cuda_time_total", row_limit=rows) + "\n\nby input shape:\n"
                    + prof.key_averages(group_by_input_shape=True).table(sort_by="self_cuda_time_total",
                                                                         row_limit=2 * rows))


def measure_memory(ip2p_models, mv_models, rows, meta, renders, views, size) -> None:
    """Peak CUDA memory with both models loaded and one graphed step of each, in the fastest
    eager/graph configuration of InstructPix2Pix measured so far."""
    best = min((r for r in rows if r["guidance"] == "ip2p"), key=lambda r: r["total_ms"])
    dt, cl, bench = best["dtype"], best["channels_last"], best["cudnn_benchmark"]
    torch.backends.cudnn.benchmark = bench
    for models in (ip2p_models, mv_models):
        freeze(models.unet, dtype=DTYPE_NAMES[dt])
        freeze(models.vae, dtype=DTYPE_NAMES[dt])
        set_format(models, cl, best.get("fused", "off"))
    for graph, mode in ((False, "eager"), (True, "graph")):
        gc.collect()
        torch.cuda.empty_cache()
        torch.cuda.reset_peak_memory_stats()
        ip, mv = make_guidances(ip2p_models, mv_models, graph=graph, size=size)
        ip.grad(renders, views)
        mv.grad(renders, views)
        torch.cuda.synchronize()
        meta[f"peak_memory_gib_both_models_{mode}_step"] = torch.cuda.max_memory_allocated() / 2 ** 30
        if not graph:
            del ip, mv
    meta["peak_reserved_gib"] = torch.cuda.max_memory_reserved() / 2 ** 30
    meta["memory_config"] = f"{dt} channels_last={cl} cudnn_benchmark={bench} fused={best.get('fused', 'off')} graph"
    print("memory:", {k: v for k, v in meta.items() if "memory" in k or "reserved" in k}, flush=True)
    del ip, mv
    gc.collect()
    torch.cuda.empty_cache()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--size", default=None, help="tiny or full (default: full on CUDA, tiny on CPU)")
    ap.add_argument("--render", type=int, default=None, help="render side in pixels (default 512 full, 64 tiny)")
    ap.add_argument("--reps", type=int, default=10)
    ap.add_argument("--dtypes", default=None, help="comma list of bf16,fp16,fp32")
    ap.add_argument("--modes", default=None, help="comma list of eager,graph,compile")
    ap.add_argument("--budget-s", type=float, default=420.0, help="skip remaining variants after this many seconds")
    ap.add_argument("--out", type=Path, default=None, help="JSON file for the raw rows")
    ap.add_argument("--profile-dir", type=Path, default=None, help="write torch.profiler tables here (CUDA)")
    ap.add_argument("--fused", default=None,
                    help="comma list of off,vae,all: torch's GroupNorm everywhere, tiger's fused GroupNorm+SiLU "
                         "in channels-last for the VAEs (the loaders' default on CUDA) or for the VAEs and the "
                         "UNets; default off,vae on CUDA, off on CPU")
    ap.add_argument("--quick", action="store_true",
                    help="eager and graph only in NCHW with cuDNN autotuning (no channels-last UNet variants)")
    args = ap.parse_args()
    t_start = time.perf_counter()
    cuda = args.device.startswith("cuda")
    size = args.size or ("full" if cuda else "tiny")
    res = args.render or (512 if size == "full" else 64)
    dtypes = (args.dtypes or ("bf16,fp16" if cuda else "fp32")).split(",")
    modes = (args.modes or ("eager,graph,compile_vae,compile" if cuda else "eager")).split(",")
    fused_levels = (args.fused or ("off,vae" if cuda else "off")).split(",")
    if any(f not in FUSED_LEVELS for f in fused_levels):
        ap.error(f"--fused takes a comma list of {', '.join(FUSED_LEVELS)}, got '{args.fused}'")
    torch.manual_seed(0)
    tok = tokenizer(Path(tempfile.mkdtemp()))
    ip2p_models, mv_models = build_models(size, args.device, DTYPE_NAMES[dtypes[0]], tok)
    renders = torch.rand(4, 3, res, res, device=args.device)
    views = ViewBatch(cameras=ring(4, res), originals=torch.rand(4, 3, res, res, device=args.device),
                      view_ids=torch.arange(4), object_center=torch.zeros(3))
    timer = (lambda fn: cuda_time_ms(fn, iters=args.reps, warmup=3)) if cuda else (lambda fn: cpu_time_ms(fn, iters=args.reps, warmup=1))
    rows: list[dict] = []
    meta = {"device": torch.cuda.get_device_name() if cuda else "cpu", "torch": torch.__version__, "size": size,
            "render": res}
    try:
        import diffusers

        meta["diffusers"] = diffusers.__version__
    except ImportError:
        pass

    def save() -> None:
        if args.out is not None:
            args.out.write_text(json.dumps({"meta": meta, "rows": rows}, indent=1))

    flops: dict[str, float] = {}
    variants = []  # most informative first: the time budget cuts the tail
    for fused in fused_levels:
        for mode in modes:
            for dt in dtypes:
                if not cuda:
                    variants.append((fused, dt, mode, False, False))
                elif args.quick and mode in ("eager", "graph"):
                    variants.append((fused, dt, mode, False, True))
                elif mode == "eager":
                    variants += [(fused, dt, mode, cl, bench) for cl in (False, True) for bench in (False, True)]
                elif mode == "graph":
                    variants += [(fused, dt, mode, cl, True) for cl in (False, True)]
                else:  # compiled: channels-last lets inductor's GroupNorm kernels and cuDNN's NHWC convs meet
                    variants += [(fused, dt, mode, cl, True) for cl in (True, False)]
    # the fused norms replace modules for good: every unfused variant first; then, on CUDA,
    # all bf16 compiled variants before the fp16 ones
    variants.sort(key=lambda v: (FUSED_LEVELS.index(v[0]), cuda and v[2].startswith("compile"),
                                 cuda and v[2].startswith("compile") and v[1] != dtypes[0]))
    fused_now = "off"
    for fused, dt, mode, cl, bench in variants:
        if time.perf_counter() - t_start > args.budget_s:
            print(f"budget reached: skipping {dt} {mode} channels_last={cl} cudnn_benchmark={bench} "
                  f"fused={fused}", flush=True)
            continue
        while FUSED_LEVELS.index(fused_now) < FUSED_LEVELS.index(fused):  # replacing modules is for good
            fused_now = FUSED_LEVELS[FUSED_LEVELS.index(fused_now) + 1]
            for models in (ip2p_models, mv_models):
                apply_fused_norms(models.vae if fused_now == "vae" else models.unet, True)
        if cuda and mode.startswith("compile") and "peak_memory_gib_both_models_graph_step" not in meta:
            measure_memory(ip2p_models, mv_models, rows, meta, renders, views, size)
        torch.backends.cudnn.benchmark = bench
        for models in (ip2p_models, mv_models):
            freeze(models.unet, dtype=DTYPE_NAMES[dt])
            freeze(models.vae, dtype=DTYPE_NAMES[dt])
            set_format(models, cl, fused)
        if mode.startswith("compile"):
            for models in (ip2p_models, mv_models):
                if mode == "compile":
                    models.unet.forward = torch.compile(models.unet.forward)
                models.vae.encoder.forward = torch.compile(models.vae.encoder.forward)
        ip, mv = make_guidances(ip2p_models, mv_models, graph=mode != "eager", size=size)
        for name, g in (("ip2p", ip), ("mvdream", mv)):
            t0 = time.perf_counter()
            row = {"guidance": name, "dtype": dt, "mode": mode, "channels_last": cl, "cudnn_benchmark": bench,
                   "fused": fused}
            if mode == "eager":
                row.update(split_ms(g, renders, views, cuda, args.reps))
            row["total_ms"] = timer(lambda: g.grad(renders, views))
            key = name
            if key not in flops and mode == "eager":
                flops[key] = count_flops(lambda: g.grad(renders, views))
            if key in flops:
                row["tflop"] = flops[key] / 1e12
                row["tflop_per_s"] = flops[key] / 1e12 / (row["total_ms"] / 1e3)
                if cuda:
                    row["fraction_of_790"] = row["tflop_per_s"] / H100_BF16_TFLOPS
            row["setup_s"] = time.perf_counter() - t0
            rows.append(row)
            print(json.dumps(row), flush=True)
            save()
        if cuda and args.profile_dir is not None and mode == "eager" and not cl and bench and dt == dtypes[0]:
            args.profile_dir.mkdir(parents=True, exist_ok=True)
            tag = dt if fused == "off" else f"{dt}_fused_{fused}"
            profile_table(lambda: ip.grad(renders, views), args.profile_dir / f"profile_ip2p_{tag}.txt")
            profile_table(lambda: mv.grad(renders, views), args.profile_dir / f"profile_mvdream_{tag}.txt")
        if mode.startswith("compile"):
            for models in (ip2p_models, mv_models):
                for module in (models.unet, models.vae.encoder):
                    module.__dict__.pop("forward", None)  # back to the class method
            torch._dynamo.reset()
        del ip, mv
        gc.collect()
        if cuda:
            torch.cuda.empty_cache()
    if cuda and "peak_memory_gib_both_models_graph_step" not in meta:
        measure_memory(ip2p_models, mv_models, rows, meta, renders, views, size)
    meta["wall_s"] = time.perf_counter() - t_start
    save()
    cols = ["guidance", "dtype", "mode", "channels_last", "cudnn_benchmark", "fused", "encode_ms", "unet_ms", "backward_ms",
            "total_ms", "tflop", "tflop_per_s", "fraction_of_790", "setup_s"]
    print_table([{c: r.get(c, "-") for c in cols} for r in rows], title=f"one 4-view SDS gradient, {meta}")
    if cuda and rows:
        targets = {"ip2p": 70.0, "mvdream": 18.0}  # the acceptance targets on the H100
        for name, target in targets.items():
            mine = [r for r in rows if r["guidance"] == name]
            if mine:
                b = min(mine, key=lambda r: r["total_ms"])
                print(f"best {name}: {b['total_ms']:.1f} ms ({b['dtype']} {b['mode']} channels_last={b['channels_last']} "
                      f"cudnn_benchmark={b['cudnn_benchmark']} fused={b['fused']}), target <= {target} ms: "
                      f"{'met' if b['total_ms'] <= target else 'NOT met'}")
        peak = meta.get("peak_memory_gib_both_models_graph_step")
        if peak is not None:
            print(f"peak memory, both models + one step each: {peak * 2 ** 30 / 1e9:.2f} GB, target <= 12 GB: "
                  f"{'met' if peak * 2 ** 30 / 1e9 <= 12 else 'NOT met'}")


if __name__ == "__main__":
    main()
