"""Benchmark of the language-feature stages (SPEC §4): per-image time of each stage, and the ops
against plain PyTorch versions (time and error vs a float64 reference).

CPU (here):  python -m benchmarks.features --device cpu --models tiny
GPU:         python -m benchmarks.features --device cuda --models full --out-long-side 1920
``--models full`` builds CLIP ViT-B/16 and SAM ViT-H with random weights from their configs (the
real models' cost); ``tiny`` uses the test-size models. Input images are 1920x1080.
The mask stages (box NMS, clean-up, mask NMS, id map, masked average, PCA statistics) and the
mask-NMS table run on SAM-like synthetic mask sets of 100 / 300 / 1000 masks
(``benchmarks/masks.py``): random SAM weights produce no realistic masks. The NMS table runs the
pairwise baselines in full (nothing extrapolated) and asserts they keep the masks ours keeps.
"""
from __future__ import annotations

import argparse
import math
import os

import torch
import torch.nn.functional as F

from benchmarks.common import median_time, print_table, rel_err, timed  # noqa: E402

import tiger  # noqa: E402,F401
from tiger.language.featup import ImplicitConfig, ImplicitUpsampler, JBUStack, upsample_features  # noqa: E402
from tiger.language.maskclip import MaskCLIP, normalize_images, resize_for_patches  # noqa: E402
from tiger.language.pca import StreamingPCA  # noqa: E402
from tiger.language.sam_masks import SamMaskConfig, SamMaskGenerator, SamMasks, masks_to_boxes  # noqa: E402
from tiger.ops.jbu import adaptive_conv  # noqa: E402
from tiger.ops.masked_average import masked_average  # noqa: E402
from tiger.ops.nms import box_nms, mask_intersections, mask_nms  # noqa: E402
from benchmarks.masks import langsplat_loop, matmul_counts, pairwise_loop, realistic_masks  # noqa: E402


def synthetic_image(h: int, w: int, seed: int = 0) -> torch.Tensor:
    """A photo-like test image: smooth colour gradients plus discs and boxes with sharp edges."""
    g = torch.Generator().manual_seed(seed)
    yy, xx = torch.meshgrid(torch.linspace(0, 1, h), torch.linspace(0, 1, w), indexing="ij")
    img = torch.stack([0.3 + 0.4 * xx, 0.2 + 0.5 * yy, 0.6 - 0.3 * xx * yy])
    for _ in range(25):
        cy, cx, r = torch.rand(3, generator=g).tolist()
        col = torch.rand(3, 1, generator=g)
        sel = (yy - cy) ** 2 + ((xx - cx) * w / h) ** 2 <= (0.03 + 0.15 * r) ** 2
        img[:, sel] = col
    return img.clamp(0, 1)


def bench_ops(dev: torch.device, h: int, w: int) -> list[dict]:
    rows = []
    cuda = dev.type == "cuda"
    # masked average: a 512-d feature map with 300 masks
    p, c, m = h * w, 512, 300
    feats = torch.randn(p, c, device=dev)
    ids = torch.randint(-1, m, (h // 8, w // 8), device=dev)
    ids = F.interpolate(ids[None, None].float(), size=(h, w), mode="nearest")[0, 0].long().reshape(-1)
    ref64 = masked_average(feats.double(), ids, m)[0] if not cuda else masked_average(feats.double().cpu(), ids.cpu(), m)[0]

    def torch_masked_average():
        valid = ids >= 0
        sums = torch.zeros(m, c, device=dev).index_add_(0, ids[valid], feats[valid])
        cnt = torch.bincount(ids[valid], minlength=m).clamp_min(1)
        return torch.where(valid[:, None], (sums / cnt[:, None])[ids.clamp_min(0)], feats)

    for name, fn in [("tiger::masked_average", lambda: masked_average(feats, ids, m)[0]),
                     ("torch index_add", torch_masked_average)]:
        t = median_time(fn, repeats=5, cuda=cuda)
        rows.append({"op": "masked average", "impl": name, "size": f"{h}x{w}x{c}, M={m}", "seconds": t,
                     "rel_err_vs_f64": rel_err(fn(), ref64), "note": ""})
    # adaptive conv: the last JBU stage (512 channels, 7x7 kernels)
    hh, ww = (448, 448) if cuda else (80, 80)
    inp = torch.randn(1, 512, hh + 6, ww + 6, device=dev)
    filt = torch.softmax(torch.randn(1, hh, ww, 49, device=dev), -1).view(1, hh, ww, 7, 7)
    ref = adaptive_conv(inp.double().cpu(), filt.double().cpu())

    def unfold_conv():
        cols = F.unfold(inp, 7).view(1, 512, 49, hh, ww)
        return torch.einsum("bcphw,bhwp->bchw", cols, filt.view(1, hh, ww, 49))

    for name, fn in [("tiger::adaptive_conv", lambda: adaptive_conv(inp, filt)), ("torch unfold+einsum", unfold_conv)]:
        t = median_time(fn, repeats=5 if cuda else 3, cuda=cuda)
        rows.append({"op": "adaptive conv", "impl": name, "size": f"512x{hh}x{ww}, k=7", "seconds": t,
                     "rel_err_vs_f64": rel_err(fn(), ref), "note": ""})
    boxes = masks_to_boxes(realistic_masks(1000, h // 4, w // 4, dev)[0]).float()
    sc = torch.rand(1000, device=dev)
    rows.append({"op": "box NMS M=1000", "impl": "tiger::box_nms", "size": "", "seconds":
                 median_time(lambda: box_nms(boxes, sc, 0.7), repeats=5, cuda=cuda), "rel_err_vs_f64": 0.0,
                 "note": ""})
    return rows


def bench_mask_nms(dev: torch.device, h: int, w: int, counts: list[int], langsplat_max: int) -> list[dict]:
    """tiger::mask_nms against full runs of the pairwise algorithm (same kept set asserted) and
    against matrix-product intersection counts, on SAM-like mask sets (benchmarks/masks.py)."""
    rows = []
    cuda = dev.type == "cuda"

    def row(op, impl, seconds, note):
        rows.append({"op": op, "impl": impl, "size": f"{h}x{w}", "seconds": seconds, "note": note})
        print(f"  {op} | {impl}: {seconds:.4f} s  {note}", flush=True)  # survives a time-out

    for mm in counts:
        masks, scores = realistic_masks(mm, h, w, dev, seed=mm)
        op = f"mask NMS M={mm}"
        keep = mask_nms(masks, scores)
        t_op = median_time(lambda: mask_nms(masks, scores), repeats=5, cuda=cuda)
        counts_ref = mask_intersections(masks)
        ov = counts_ref.double()
        iou = ov / (ov.diagonal()[:, None] + ov.diagonal()[None] - ov).clamp_min(1)
        iou.fill_diagonal_(0)
        row(op, "tiger::mask_nms", t_op, f"{mm} -> {keep.numel()} kept; {int((iou > 0.8).sum()) // 2} pairs "
            f"IoU > 0.8, {int(((iou > 0.5) & (iou <= 0.8)).sum()) // 2} in (0.5, 0.8]")
        t_cnt = median_time(lambda: mask_intersections(masks), repeats=5, cuda=cuda)
        row(op, "tiger::mask_intersections (counts only)", t_cnt, "popcount of bit-packed masks")
        for kind in (["float32", "tf32", "int8"] if cuda else ["float32"]):
            try:
                exact = bool(torch.equal(matmul_counts(masks, kind), counts_ref))
                t = median_time(lambda: matmul_counts(masks, kind), repeats=5, cuda=cuda)
                row(op, f"torch matmul {kind} (counts only)", t, f"counts exact: {exact}")
            except (RuntimeError, torch.cuda.OutOfMemoryError) as exc:  # pragma: no cover - device dependent
                row(op, f"torch matmul {kind} (counts only)", float("nan"), f"failed: {str(exc)[:80]}")
        keep_pw, t_pw = timed(lambda: pairwise_loop(masks, scores), dev)
        same = keep_pw.tolist() == keep.tolist()
        row(op, "pairwise loop, one host read per pair (full run)", t_pw,
            f"same kept set: {same}; ours {t_pw / t_op:.0f}x faster")
        assert same, f"mask NMS M={mm}: tiger keeps {keep.tolist()}, the pairwise loop {keep_pw.tolist()}"
        if mm <= langsplat_max:
            keep_ls, t_ls = timed(lambda: langsplat_loop(masks, scores), dev)
            same = keep_ls.tolist() == keep.tolist()
            row(op, "LangSplat's loop as written (full run)", t_ls, f"same kept set: {same}; ours {t_ls / t_op:.0f}x faster")
            assert same, f"mask NMS M={mm}: tiger keeps {keep.tolist()}, LangSplat's loop {keep_ls.tolist()}"
        del masks
        if cuda:
            torch.cuda.empty_cache()
    return rows


def build_models(kind: str, dev: torch.device, dtype: torch.dtype):
    from tiger.testing.random_models import clip_config, random_sam, write_byte_level_clip_tokenizer
    import tempfile
    import transformers

    with torch.device(dev):
        torch.manual_seed(0)
        clip_model = transformers.CLIPModel(clip_config(kind)).eval()
    tok_dir = tempfile.mkdtemp()
    write_byte_level_clip_tokenizer(tok_dir)
    tok = transformers.CLIPTokenizer.from_pretrained(tok_dir)
    clip = MaskCLIP(clip_model.to(dtype), tok)
    with torch.device(dev):
        sam = random_sam(kind).to(dtype)
    return clip, sam


def bench_pipeline(dev, kind, dtype, img_hw, out_hw, clip_long, steps, n_views, points_per_batch,
                   mask_counts) -> list[dict]:
    clip, sam_model = build_models(kind, dev, dtype)
    image = synthetic_image(*img_hw).to(dev)
    rows = []

    def row(stage, seconds, note=""):
        rows.append({"stage": stage, "seconds/image": seconds, "note": note})
        print(f"  {stage}: {seconds:.3f} s  {note}", flush=True)  # partial results survive a time-out

    clip_in = resize_for_patches(image[None], clip_long)[0]
    clip(clip_in[None])  # warm-up
    lr, t = timed(lambda: clip(clip_in[None]), dev)
    row("MaskCLIP", t, f"{tuple(clip_in.shape[-2:])} -> {tuple(lr.shape[-2:])} patches, {dtype}")
    d = lr.shape[1]

    jbu = JBUStack(d).to(dev).eval()
    norm = lambda x: normalize_images(x, "imagenet")  # noqa: E731
    upsample_features(clip_in, clip, out_hw, "jbu", jbu=jbu, lowres=lr[0], guidance_normalizer=norm)
    hr_jbu, t = timed(lambda: upsample_features(clip_in, clip, out_hw, "jbu", jbu=jbu, lowres=lr[0],
                                                guidance_normalizer=norm), dev)
    row("FeatUp JBU", t, f"16x stack + resize to {out_hw}")

    if steps > 0:
        cfg = ImplicitConfig(steps=steps, n_views=n_views)
        up, t_fit = timed(lambda: ImplicitUpsampler.fit(clip_in, clip, cfg), dev)
        hr, t_eval = timed(lambda: up(out_hw), dev)
        row("FeatUp implicit", t_fit + t_eval, f"fit {t_fit:.2f}s ({steps} steps, {n_views} views) + eval {t_eval:.2f}s")
    else:
        hr = hr_jbu

    lenient = SamMaskConfig(points_per_batch=points_per_batch, pred_iou_thresh=-1e9, stability_score_thresh=0.0,
                            precision="fp32")  # the model's own dtype (--dtype) decides
    gen = SamMaskGenerator(sam_model, lenient)
    gen.predict(image, (64, 64))  # warm-up
    pixels, _ = gen.preprocess(image)
    _, t_enc = timed(lambda: sam_model.get_image_embeddings(pixels.to(dtype)), dev)
    (masks, _, _), t_pred = timed(lambda: gen.predict(image, out_hw), dev)
    row("SAM encoder (ViT)", t_enc, f"{sam_model.config.vision_config.num_hidden_layers} blocks, {dtype}")
    row("SAM 32x32 prompts + upscale", t_pred - t_enc, f"{masks.shape[0]} masks (random weights, filters off)")
    del masks
    shared_fast = sum(r["seconds/image"] for r in rows if r["stage"] != "FeatUp implicit")
    shared_quality = sum(r["seconds/image"] for r in rows if r["stage"] != "FeatUp JBU")
    # Random SAM weights give no realistic masks: the mask stages run on SAM-like synthetic sets
    # (benchmarks/masks.py) of each size, as SAM's real outputs would reach them.
    feats = F.normalize(hr.float(), dim=0).permute(1, 2, 0).reshape(-1, d)
    cfg = SamMaskConfig(precision="fp32")
    for mm in mask_counts:
        masks, scores = realistic_masks(mm, *out_hw, dev, seed=mm)
        first = len(rows)
        keep, t_box = timed(lambda: box_nms(masks_to_boxes(masks), scores, cfg.box_nms_thresh), dev)
        masks, scores = masks[keep], scores[keep]
        row(f"[M={mm}] box NMS", t_box, f"{mm} -> {masks.shape[0]} masks")
        (masks, changed), t_clean = timed(lambda: gen._clean(masks), dev)
        big = masks.flatten(1).sum(1) >= cfg.min_mask_region_area
        masks, scores = masks[big], scores[big]
        row(f"[M={mm}] small-region clean-up", t_clean, f"{int(changed.sum())} changed, {masks.shape[0]} >= "
            f"{cfg.min_mask_region_area} px")
        keep, t_mnms = timed(lambda: mask_nms(masks, scores, cfg.mask_nms_iou, cfg.mask_nms_score,
                                              cfg.mask_nms_inner), dev)
        row(f"[M={mm}] mask NMS", t_mnms, f"{masks.shape[0]} -> {keep.numel()} masks")
        sm = SamMasks(masks[keep], scores[keep], torch.ones_like(scores[keep]))
        ids, t_ids = timed(lambda: sm.id_map().reshape(-1), dev)
        (_, means, counts), t_ma = timed(lambda: masked_average(feats, ids, sm.masks.shape[0]), dev)
        row(f"[M={mm}] id map + masked average", t_ids + t_ma, f"{sm.masks.shape[0]} masks, "
            f"{100 * float((ids >= 0).float().mean()):.0f} % of pixels in a mask")
        acc = StreamingPCA(d, min(64, d))
        _, t_pca = timed(lambda: acc.update(torch.cat([means, feats[ids < 0]]),
                                            torch.cat([counts.float(), torch.ones(int((ids < 0).sum()), device=dev)])), dev)
        row(f"[M={mm}] PCA statistics", t_pca)
        mask_t = sum(r["seconds/image"] for r in rows[first:])
        if steps > 0:
            row(f"[M={mm}] TOTAL (implicit, paper)", shared_quality + mask_t)
        row(f"[M={mm}] TOTAL (JBU, fast)", shared_fast + mask_t)
        del masks, sm, ids
        if dev.type == "cuda":
            torch.cuda.empty_cache()
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    ap.add_argument("--models", choices=["tiny", "full"], default=None)
    ap.add_argument("--image", default="1080x1920", help="HxW of the input image")
    ap.add_argument("--out-long-side", type=int, default=None, help="feature-map long side (default: 480 CPU, 1920 GPU)")
    ap.add_argument("--clip-long-side", type=int, default=None, help="MaskCLIP input long side (448 GPU, 224 CPU)")
    ap.add_argument("--steps", type=int, default=None,
                    help="implicit FeatUp steps (default 1200 GPU, 10 CPU; 0 skips the implicit upsampler)")
    ap.add_argument("--views", type=int, default=None, help="implicit FeatUp jittered views (default 3000 GPU, 20 CPU)")
    ap.add_argument("--mask-counts", default=None,
                    help="SAM-like mask set sizes for the mask stages and the NMS table (default 100,300,1000 "
                         "GPU, 100,300 CPU)")
    ap.add_argument("--langsplat-max", type=int, default=300,
                    help="run LangSplat's loop as written up to this mask count (it needs ~0.4 ms per pair)")
    ap.add_argument("--skip-ops", action="store_true")
    ap.add_argument("--skip-nms", action="store_true")
    ap.add_argument("--skip-pipeline", action="store_true")
    args = ap.parse_args()
    dev = torch.device(args.device)
    cuda = dev.type == "cuda"
    kind = args.models or ("full" if cuda else "tiny")
    dtype = torch.bfloat16 if cuda else torch.float32  # random full-size weights overflow fp16
    ih, iw = (int(v) for v in args.image.split("x"))
    long_side = args.out_long_side or (1920 if cuda else 480)
    s = long_side / max(ih, iw)
    out_hw = (round(ih * s), round(iw * s))
    print(f"device {dev} ({torch.cuda.get_device_name(dev) if cuda else os.cpu_count()}), models {kind}, "
          f"image {ih}x{iw}, feature maps {out_hw[0]}x{out_hw[1]}")
    counts = [int(c) for c in (args.mask_counts or ("100,300,1000" if cuda else "100,300")).split(",")]
    # Longest last (LangSplat's loop at the largest count): a time-out then loses only that row.
    if not args.skip_pipeline:
        steps = args.steps if args.steps is not None else (1200 if cuda else 10)
        rows = bench_pipeline(dev, kind, dtype, (ih, iw), out_hw, args.clip_long_side or (448 if cuda else 224),
                              steps, args.views or (3000 if cuda else 20), 256 if cuda else 64, counts)
        print_table(rows, f"per-image stage times ({kind} models, {dtype})")
    if not args.skip_ops:
        print_table(bench_ops(dev, *out_hw), "ops (median seconds; errors vs float64)")
    if not args.skip_nms:
        print_table(bench_mask_nms(dev, *out_hw, counts, args.langsplat_max),
                    "mask NMS on SAM-like mask sets (seconds; kept sets asserted equal)")

if __name__ == "__main__":
    main()
