"""Benchmark of the implicit FeatUp fit (SPEC §4): the fast fit (``ImplicitConfig.method="fast"``,
the default) against the reference loop, per image: time, FLOPs, TFLOP/s achieved, and the
per-pixel cosine similarity of the fast fit's upsampled map with the reference fit's.

GPU (full-size random CLIP ViT-B/16, a 1080x1920 image, the paper's settings; < 4 min on an H100):
    python -m benchmarks.featup_implicit --device cuda
CPU (reduced size: a 224x398 image, a small random CLIP, fewer steps and views):
    python -m benchmarks.featup_implicit --device cpu

Both fits use the same seed (the same jitters, view picks and initial weights); the dropout masks
differ by construction, so the fast fit with another seed is also compared with the fast fit
(the run-to-run spread of the fit itself). FLOPs are counted for the work the fit does: the
backbone passes of the jittered views (``torch.utils.flop_counter`` on one view, times the views),
and per step the network over all pixels at the fit resolution, the blur, the jitter resampling
and the attention downsampler's logits and window sums (forward + backward = 3x forward).
"""
from __future__ import annotations

import argparse
import dataclasses

import torch
import torch.nn.functional as F

import tiger  # noqa: F401
from benchmarks.common import print_table, sync, timed
from benchmarks.features import synthetic_image
from tiger.language.featup import ImplicitConfig, ImplicitUpsampler
from tiger.language.featup_fit import window_geometry
from tiger.language.maskclip import MaskCLIP, resize_for_patches

H100_BF16_TFLOPS = 790.0  # dense bf16 tensor-core peak used for the share (the figure)
H100_TF32_TFLOPS = 400.0


def build_clip(kind: str, dev: torch.device) -> MaskCLIP:
    """MaskCLIP on a randomly initialised CLIP (``full``: ViT-B/16 sizes; ``tiny``: the tests')."""
    import tempfile

    import transformers

    from tiger.testing.random_models import clip_config, write_byte_level_clip_tokenizer

    with torch.device(dev):
        torch.manual_seed(0)
        model = transformers.CLIPModel(clip_config(kind)).eval()
    tok_dir = tempfile.mkdtemp()
    write_byte_level_clip_tokenizer(tok_dir)
    return MaskCLIP(model, transformers.CLIPTokenizer.from_pretrained(tok_dir))


def backbone_flops_per_view(clip: MaskCLIP, clip_in: torch.Tensor) -> float:
    from torch.utils.flop_counter import FlopCounterMode

    with torch.no_grad(), FlopCounterMode(display=False) as counter:
        clip(clip_in[None])
    return float(counter.get_total_flops())


def fit_flops(h: int, w: int, fh: int, fw: int, cfg: ImplicitConfig, backbone_per_view: float) -> dict:
    """FLOPs of one fit (dict of parts, and 'total'); multiply-add = 2 FLOPs, backward = 2x forward."""
    k = cfg.proj_dim
    c = k + 1  # magnitude + coefficients
    d = 2 * 5 * cfg.n_freqs + 3
    px = h * w
    net = px * 2 * (d * k + 2 * k * k)
    blur = c * px * 2 * 2 * 5  # separable 5-tap blur
    kk = window_geometry(h, w, (fh, fw), cfg.kernel_size)[0] ** 2
    per_jitter = 8 * c * px + fh * fw * kk * (2 * c + 2 * c)  # bilinear jitter + logits + weighted sum
    step = 3 * (net + blur + cfg.jitters_per_step * per_jitter)
    parts = {"backbone": backbone_per_view * cfg.n_views, "network": 3.0 * net * cfg.steps,
             "downsampler+jitter+blur": 3.0 * (blur + cfg.jitters_per_step * per_jitter) * cfg.steps}
    parts["total"] = parts["backbone"] + step * cfg.steps
    return parts


def cosine_stats(a: torch.Tensor, b: torch.Tensor) -> dict:
    cos = F.cosine_similarity(a.float(), b.float(), dim=0).flatten().cpu()
    q = torch.quantile(cos[torch.randperm(cos.numel())[:1_000_000]].double(), torch.tensor([0.001, 0.01, 0.05, 0.5]).double())
    return {"mean": cos.mean().item(), "min": cos.min().item(), "p0.1": q[0].item(), "p1": q[1].item(),
            "p5": q[2].item(), "median": q[3].item(), "frac>=0.99": (cos >= 0.99).float().mean().item()}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    ap.add_argument("--models", choices=("full", "tiny"), default=None, help="random CLIP size (default: full on CUDA, tiny on CPU)")
    ap.add_argument("--image", type=int, nargs=2, default=None, metavar=("H", "W"),
                    help="input image size (default 1080 1920 on CUDA, 224 398 on CPU)")
    ap.add_argument("--clip-long-side", type=int, default=None, help="fit resolution's long side (default 448 CUDA, 224 CPU)")
    ap.add_argument("--steps", type=int, default=None, help="fit steps (default 1200 CUDA, 150 CPU)")
    ap.add_argument("--views", type=int, default=None, help="jittered views (default 3000 CUDA, 60 CPU)")
    ap.add_argument("--no-reference", action="store_true", help="time the fast fit only")
    ap.add_argument("--no-fp32", action="store_true", help="skip the fast fit in float32")
    ap.add_argument("--profile", action="store_true", help="print a profile of 20 fast steps (64 views)")
    args = ap.parse_args()
    dev = torch.device(args.device)
    cuda = dev.type == "cuda"
    kind = args.models or ("full" if cuda else "tiny")
    img_hw = tuple(args.image or ((1080, 1920) if cuda else (224, 398)))
    clip_long = args.clip_long_side or (448 if cuda else 224)
    steps = args.steps or (1200 if cuda else 150)
    views = args.views or (3000 if cuda else 60)

    clip = build_clip(kind, dev)
    image = synthetic_image(*img_hw).to(dev)
    clip_in = resize_for_patches(image[None], clip_long)[0]
    h, w = clip_in.shape[-2:]
    print(f"device {dev} ({torch.cuda.get_device_name(dev) if cuda else 'cpu'}), CLIP {kind}, image {img_hw}, "
          f"fit at {h}x{w}, {steps} steps, {views} views, torch {torch.__version__}", flush=True)

    base = ImplicitConfig(steps=steps, n_views=views)
    # warm-up (cuDNN/cuBLAS plans, allocator) on a short fit of each path
    for method in ("fast",) + (() if args.no_reference else ("reference",)):
        ImplicitUpsampler.fit(clip_in, clip, dataclasses.replace(base, steps=3, n_views=8, method=method))
    sync(dev)

    rows, maps = [], {}
    runs = [("fast bf16", dataclasses.replace(base, method="fast", precision="bf16"))]
    if not args.no_fp32:
        runs.append(("fast fp32", dataclasses.replace(base, method="fast", precision="fp32")))
    runs.append(("fast bf16 seed 1", dataclasses.replace(base, method="fast", precision="bf16", seed=1)))
    if not args.no_reference:
        runs.append(("reference", dataclasses.replace(base, method="reference")))
    bb = backbone_flops_per_view(clip, clip_in)
    with torch.no_grad():
        fh, fw = clip(clip_in[None]).shape[-2:]
    flops = fit_flops(h, w, fh, fw, base, bb)
    # the backbone share of the fast fit: the jittered views' features alone
    from tiger.language.featup import sample_jitter
    from tiger.language.featup_fit import featurize_jitters, jitter_params

    gen = torch.Generator().manual_seed(0)
    pad = min(int(round(base.max_pad * min(h, w) / 224)), min(h, w) - 1)
    params = jitter_params([sample_jitter(h, w, pad, base.max_zoom, True, gen) for _ in range(views)], h, w, dev)
    _, t_bb = timed(lambda: featurize_jitters(clip_in[None], clip, params, base.featurize_batch, "bf16",
                                              lambda f: f), dev)
    print(f"  backbone of {views} jittered views (fast path, bf16 on CUDA): {t_bb:.2f} s, "
          f"{bb * views / t_bb / 1e12:.1f} TFLOP/s", flush=True)
    if args.profile:
        from torch.profiler import ProfilerActivity, profile

        acts = [ProfilerActivity.CPU] + ([ProfilerActivity.CUDA] if cuda else [])
        with profile(activities=acts) as prof:
            ImplicitUpsampler.fit(clip_in, clip, dataclasses.replace(base, steps=20, n_views=64))
            sync(dev)
        print(prof.key_averages().table(sort_by="cuda_time_total" if cuda else "cpu_time_total", row_limit=25))
    for name, cfg in runs:
        up, t_fit = timed(lambda: ImplicitUpsampler.fit(clip_in, clip, cfg), dev)
        hr, t_eval = timed(lambda: up(img_hw), dev)
        maps[name] = hr
        tflops = flops["total"] / t_fit / 1e12
        rows.append({"fit": name, "fit s": t_fit, "eval s": t_eval, "s/image": t_fit + t_eval,
                     "TFLOP/s": tflops, "% of 790 bf16": 100 * tflops / H100_BF16_TFLOPS,
                     "final loss": up.history[-1]})
        print(f"  {name}: fit {t_fit:.2f} s + eval {t_eval:.2f} s, {tflops:.1f} TFLOP/s", flush=True)
    print(f"\nFLOPs per fit: " + ", ".join(f"{k} {v / 1e12:.2f} TFLOP" for k, v in flops.items()))
    floor = flops["total"] / (H100_BF16_TFLOPS * 1e12)
    print(f"FLOP floor on an H100: {floor:.3f} s at {H100_BF16_TFLOPS:.0f} TFLOP/s bf16, "
          f"{flops['total'] / (H100_TF32_TFLOPS * 1e12):.3f} s at {H100_TF32_TFLOPS:.0f} TFLOP/s TF32")
    print_table(rows, "implicit FeatUp fit, per image")

    ref = "reference" if "reference" in maps else "fast fp32" if "fast fp32" in maps else None
    cmp_rows = []
    for name in maps:
        if ref is not None and name != ref:
            cmp_rows.append({"map": name, "vs": ref, **cosine_stats(maps[name], maps[ref])})
    if "fast bf16 seed 1" in maps:
        cmp_rows.append({"map": "fast bf16 seed 1", "vs": "fast bf16", **cosine_stats(maps["fast bf16 seed 1"],
                                                                                    maps["fast bf16"])})
    print_table(cmp_rows, f"per-pixel cosine similarity at {img_hw[0]}x{img_hw[1]} ({next(iter(maps.values())).shape[0]}-d features)")


if __name__ == "__main__":
    main()
