"""Benchmark of the implicit FeatUp fit (SPEC §4): the fast fit (``ImplicitConfig.method="fast"``,
the default) against the reference loop, per image: time, FLOPs, TFLOP/s achieved, and the
per-pixel cosine similarity of the fast fit's upsampled map with the reference fit's.

GPU (full-size random CLIP ViT-B/16, a 1080x1920 image, the paper's settings; < 4 min on an H100):
    python -m benchmarks.featup_implicit --device cuda
    (``--reference-steps 300``: the reference loop, and a fast fit compared with it, at 300 steps)
CPU (reduced size: a 224x398 image, a small random CLIP, fewer steps and views):
    python -m benchmarks.featup_implicit --device cpu

Both fits use the same seed (the same jitters, view picks and initial weights); the dropout masks
differ by construction, so the fast fit with another seed is also compared with the fast fit
(the run-to-run spread of the fit itself). FLOPs are counted for the work the fit does: the
backbone passes of the jittered views (``torch.utils.flop_counter`` on one view, times the views),
and per step the network over all pixels at the fit resolution, the blur, the jitter resampling
and the attention downsampler's logits and window sums (forward + backward = 3x forward).
The fit loop's time per step is the fit's time less that of a fit with no steps (backbone, PCA,
set-up), over the steps; its floor is the larger of its FLOPs at the bf16 peak and its bytes at
the H100's HBM bandwidth, both for the network as PyTorch runs it (``loop_bytes``).
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
H100_HBM_TBPS = 3.35  # H100 SXM HBM3 bandwidth


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


def loop_bytes(h: int, w: int, fh: int, fw: int, cfg: ImplicitConfig) -> float:
    """HBM bytes of one fit step, estimated as each tensor written once and read once (forward),
    the backward twice that: the network as PyTorch runs it (float32 Fourier features and
    LayerNorm, bf16 matmul operands: 6 tensors of 2 * 5 * n_freqs + 3 channels at 4 bytes, 8 of
    proj_dim channels at 2 bytes, per pixel), the blur, magnitude and logit map (float32,
    proj_dim + 1 channels), the fused downsampler's reads of the features (each cell reads its
    (k + 2)^2 tile of proj_dim + 1 float32 channels, from L2 mostly: counted once per jitter),
    and the targets of the step's views."""
    px = h * w
    d = 2 * 5 * cfg.n_freqs + 3
    k = cfg.proj_dim
    net = px * (6 * d * 4 + 8 * k * 2)
    maps = px * (k + 1) * 4 * 4  # magnitude+coefficients, blurred, dropout input, blur-pin difference
    down = cfg.jitters_per_step * px * (k + 1) * 4
    targets = cfg.jitters_per_step * fh * fw * k * 4
    return 3.0 * 2 * (net + maps) + 3.0 * down + targets


def cosine_stats(a: torch.Tensor, b: torch.Tensor) -> dict:
    cos = F.cosine_similarity(a.float(), b.float(), dim=0).flatten().cpu()
    q = torch.quantile(cos[torch.randperm(cos.numel())[:1_000_000]].double(), torch.tensor([0.001, 0.01, 0.05, 0.5]).double())
    return {"mean": cos.mean().item(), "min": cos.min().item(), "p0.1": q[0].item(), "p1": q[1].item(),
            "p5": q[2].item(), "median": q[3].item(), "frac>=0.99": (cos >= 0.99).float().mean().item()}


def parse_variant(spec: str) -> dict:
    """``"n_views=1500,stop_change=0.01"`` -> ImplicitConfig fields, each converted to the field's type."""
    types = {f.name: f.type for f in dataclasses.fields(ImplicitConfig)}
    fields = {}
    for part in spec.split(","):
        name, sep, value = part.partition("=")
        name = name.strip()
        if not sep or name not in types:
            raise SystemExit(f"--variants: {part!r} is not FIELD=VALUE with an ImplicitConfig field "
                             f"({', '.join(types)})")
        kind = types[name] if isinstance(types[name], str) else types[name].__name__
        conv = {"int": int, "float": float, "bool": lambda v: v.lower() in ("1", "true", "yes")}.get(kind, str)
        fields[name] = conv(value.strip())
    return fields


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
    ap.add_argument("--reference-steps", type=int, default=None,
                    help="steps of the reference fit (default: --steps); when fewer, a fast fit of as many "
                         "steps is run for the comparison")
    ap.add_argument("--fast-steps", default="",
                    help="comma-separated step counts: fast fits of as many steps, each compared with the "
                         "reference fit of --reference-steps (how many steps the fast fit needs)")
    ap.add_argument("--variants", nargs="*", default=[], metavar="FIELD=VALUE[,FIELD=VALUE]",
                    help="fast fits with these ImplicitConfig fields changed (e.g. n_views=1500 or "
                         "stop_change=0.01,check_every=50), each at seeds 0 and 1 and compared with the "
                         "reference fit: whether a setting keeps the result")
    ap.add_argument("--eager", action="store_true", help="also time the fast fit without its CUDA graph")
    ap.add_argument("--compile", action="store_true",
                    help="also time the fast fit with the network through torch.compile (compiled in the warm-up)")
    ap.add_argument("--no-fp32", action="store_true", help="skip the fast fit in float32")
    ap.add_argument("--composition", action="store_true",
                    help="also time the fast fit with the network's input layers as the PyTorch composition "
                         "(ImplicitConfig.fused_network=False; the default fuses them)")
    ap.add_argument("--profile", action="store_true",
                    help="print a profile of 20 fast steps (64 views), run eagerly (no CUDA graph) so that the "
                         "table names each op")
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
    if args.compile:
        ImplicitUpsampler.fit(clip_in, clip, dataclasses.replace(base, steps=5, n_views=8, compile_network=True))
    sync(dev)

    rows, maps = [], {}
    runs = [("fast bf16", dataclasses.replace(base, method="fast", precision="bf16")),
            (f"fast bf16 all {steps} steps", dataclasses.replace(base, method="fast", precision="bf16",
                                                                 stop_change=0.0))]
    if not args.no_fp32:
        runs.append(("fast fp32", dataclasses.replace(base, method="fast", precision="fp32")))
    if args.compile:
        runs.append(("fast bf16 compiled", dataclasses.replace(base, method="fast", precision="bf16",
                                                               compile_network=True)))
    if args.composition:
        runs.append(("fast bf16 composition", dataclasses.replace(base, method="fast", precision="bf16",
                                                                  fused_network=False)))
    if args.eager and cuda:
        runs.append(("fast bf16 eager", dataclasses.replace(base, method="fast", precision="bf16", cuda_graph=False)))
    runs.append(("fast bf16 seed 1", dataclasses.replace(base, method="fast", precision="bf16", seed=1)))
    ref_steps = args.reference_steps or steps
    ref_name = "reference" if ref_steps == steps else f"reference {ref_steps} steps"
    if not args.no_reference:
        if ref_steps != steps:
            runs.append((f"fast bf16 {ref_steps} steps vs ref", dataclasses.replace(base, steps=ref_steps, stop_change=0.0)))
        runs.append((ref_name, dataclasses.replace(base, method="reference", steps=ref_steps)))
    for spec in args.variants:
        fields = parse_variant(spec)
        for seed in (0, 1):
            runs.append((f"fast bf16 {spec} seed {seed} vs ref",
                         dataclasses.replace(base, method="fast", precision="bf16", seed=seed, **fields)))
    fast_counts = [int(n) for n in args.fast_steps.split(",") if n.strip()]
    runs += [(f"fast bf16 {n} steps vs ref", dataclasses.replace(base, steps=n, stop_change=0.0)) for n in fast_counts]
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
            ImplicitUpsampler.fit(clip_in, clip, dataclasses.replace(base, steps=20, n_views=64, cuda_graph=False))
            sync(dev)
        print(prof.key_averages().table(sort_by="cuda_time_total" if cuda else "cpu_time_total", row_limit=25))
    # the fit without steps: backbone passes, PCA, set-up (subtracted to time the loop)
    setup = {}
    for precision in ("bf16", "fp32"):
        _, setup[precision] = timed(lambda: ImplicitUpsampler.fit(
            clip_in, clip, dataclasses.replace(base, steps=0, precision=precision)), dev)
    print(f"  fit set-up without steps (backbone, PCA): bf16 {setup['bf16']:.2f} s, fp32 {setup['fp32']:.2f} s",
          flush=True)
    per_step_flops = (flops["total"] - flops["backbone"]) / steps
    for name, cfg in runs:
        up, t_fit = timed(lambda: ImplicitUpsampler.fit(clip_in, clip, cfg), dev)
        hr, t_eval = timed(lambda: up(img_hw), dev)
        maps[name] = hr
        ran = len(up.history)
        featurised = up.views_featurised or cfg.n_views
        run_flops = flops["backbone"] * featurised / cfg.n_views + per_step_flops * ran
        tflops = run_flops / t_fit / 1e12
        step_ms = 1e3 * max(t_fit - setup[cfg.precision], 0.0) / max(ran, 1)
        if up.checks:
            print(f"  {name}: stopping checks (step: 1 - cos with the previous check's map): "
                  + " ".join(f"{st}: {c:.2e}" for st, c in up.checks), flush=True)
        rows.append({"fit": name, "steps": ran, "views": featurised, "fit s": t_fit, "loop ms/step": step_ms, "eval s": t_eval,
                     "s/image": t_fit + t_eval, "TFLOP/s": tflops, "% of 790 bf16": 100 * tflops / H100_BF16_TFLOPS,
                     "final loss": up.history[-1]})
        hist = torch.tensor([float(v) for v in up.history])
        windows = [f"{hist[i:i + 100].mean():.4f}" for i in range(0, len(hist), 100)]
        print(f"  {name}: loss per 100-step window: {' '.join(windows)}", flush=True)
        print(f"  {name}: fit {t_fit:.2f} s ({step_ms:.2f} ms/step) + eval {t_eval:.2f} s, {tflops:.1f} TFLOP/s",
              flush=True)
    print(f"\nFLOPs per fit: " + ", ".join(f"{k} {v / 1e12:.2f} TFLOP" for k, v in flops.items()))
    floor = flops["total"] / (H100_BF16_TFLOPS * 1e12)
    print(f"FLOP floor on an H100: {floor:.3f} s at {H100_BF16_TFLOPS:.0f} TFLOP/s bf16, "
          f"{flops['total'] / (H100_TF32_TFLOPS * 1e12):.3f} s at {H100_TF32_TFLOPS:.0f} TFLOP/s TF32")
    step_bytes = loop_bytes(h, w, fh, fw, base)
    floor_flops, floor_bytes = per_step_flops / (H100_BF16_TFLOPS * 1e12), step_bytes / (H100_HBM_TBPS * 1e12)
    print(f"fit loop per step: {per_step_flops / 1e9:.1f} GFLOP, ~{step_bytes / 1e9:.2f} GB; floor "
          f"{1e3 * max(floor_flops, floor_bytes):.3f} ms/step ({1e3 * floor_flops:.3f} ms of FLOPs at "
          f"{H100_BF16_TFLOPS:.0f} TFLOP/s, {1e3 * floor_bytes:.3f} ms of bytes at {H100_HBM_TBPS} TB/s); "
          f"{steps} steps: {steps * max(floor_flops, floor_bytes):.3f} s")
    print_table(rows, "implicit FeatUp fit, per image")

    cmp_rows = []
    for name in maps:
        ref = ref_name if name.startswith("fast bf16 ") and name.endswith(" vs ref") else (
            "reference" if "reference" in maps else "fast fp32" if "fast fp32" in maps else None)
        if ref is not None and ref in maps and name != ref and not name.startswith("reference"):
            cmp_rows.append({"map": name, "vs": ref, **cosine_stats(maps[name], maps[ref])})
    if "fast bf16 seed 1" in maps:
        cmp_rows.append({"map": "fast bf16 seed 1", "vs": "fast bf16", **cosine_stats(maps["fast bf16 seed 1"],
                                                                                    maps["fast bf16"])})
    print_table(cmp_rows, f"per-pixel cosine similarity at {img_hw[0]}x{img_hw[1]} ({next(iter(maps.values())).shape[0]}-d features)")


if __name__ == "__main__":
    main()
