"""Benchmark of the language-feature stages (SPEC §4): per-image time of each stage, and the ops
against plain PyTorch versions (time and error vs a float64 reference).

CPU (here):  python benchmarks/features.py --device cpu --models tiny
GPU:         python benchmarks/features.py --device cuda --models full --out-long-side 1920
``--models full`` builds CLIP ViT-B/16 and SAM ViT-H with random weights from their configs (the
real models' cost); ``tiny`` uses the test-size models. Input images are 1920x1080.
"""
from __future__ import annotations

import argparse
import math
import os
import sys
import time

import torch
import torch.nn.functional as F

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from common import median_time, print_table, rel_err  # noqa: E402

import tiger  # noqa: E402,F401
from tiger.language.featup import ImplicitConfig, ImplicitUpsampler, JBUStack, upsample_features  # noqa: E402
from tiger.language.maskclip import MaskCLIP, normalize_images, resize_for_patches  # noqa: E402
from tiger.language.pca import StreamingPCA  # noqa: E402
from tiger.language.sam_masks import SamMaskConfig, SamMaskGenerator, SamMasks, masks_to_boxes  # noqa: E402
from tiger.ops.jbu import adaptive_conv  # noqa: E402
from tiger.ops.masked_average import masked_average  # noqa: E402
from tiger.ops.nms import box_nms, mask_intersections, mask_nms  # noqa: E402


def sync(dev: torch.device) -> None:
    if dev.type == "cuda":
        torch.cuda.synchronize()


def timed(fn, dev):
    sync(dev)
    t = time.perf_counter()
    out = fn()
    sync(dev)
    return out, time.perf_counter() - t


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


def blob_masks(m: int, h: int, w: int, dev, seed: int = 0) -> torch.Tensor:
    """m overlapping disc masks (with duplicates and nested ones), the load mask NMS sees."""
    g = torch.Generator().manual_seed(seed)
    c = torch.rand(m, 3, generator=g)
    yy = torch.arange(h, device=dev).view(1, h, 1).float()
    xx = torch.arange(w, device=dev).view(1, 1, w).float()
    cy, cx = (c[:, 0] * h).to(dev).view(m, 1, 1), (c[:, 1] * w).to(dev).view(m, 1, 1)
    r = ((0.02 + 0.2 * c[:, 2] ** 2) * min(h, w)).to(dev).view(m, 1, 1)
    out = (yy - cy) ** 2 + (xx - cx) ** 2 <= r * r
    out[1::7] = out[0::7][: out[1::7].shape[0]]  # exact duplicates
    return out


def langsplat_mask_nms(masks, scores, iou_thr=0.8, score_thr=0.7, inner_thr=0.5, max_pairs=None):
    """LangSplat's Python mask NMS (pairwise loop over masks). With ``max_pairs`` only the first
    pairs are run and the returned time is extrapolated to all pairs."""
    scores, idx = scores.sort(0, descending=True)
    n = idx.shape[0]
    mo = masks[idx]
    area = mo.sum((1, 2), dtype=torch.float)
    iou_m = torch.zeros(n, n, device=masks.device)
    inner_m = torch.zeros(n, n, device=masks.device)
    pairs = [(i, j) for i in range(n) for j in range(i, n)]
    run = pairs if max_pairs is None else pairs[:max_pairs]
    for i, j in run:
        inter = torch.sum(torch.logical_and(mo[i], mo[j]), dtype=torch.float)
        union = torch.sum(torch.logical_or(mo[i], mo[j]), dtype=torch.float)
        iou_m[i, j] = inter / union
        if inter / area[i] < 0.5 and inter / area[j] >= 0.85:
            inner_m[i, j] = 1 - (inter / area[j]) * (inter / area[i])
        if inter / area[i] >= 0.85 and inter / area[j] < 0.5:
            inner_m[j, i] = 1 - (inter / area[j]) * (inter / area[i])
    iou_m.triu_(diagonal=1)
    keep = (iou_m.max(0).values <= iou_thr) & (scores > score_thr)
    keep &= torch.triu(inner_m, diagonal=1).max(0).values <= 1 - inner_thr
    keep &= torch.tril(inner_m, diagonal=1).max(0).values <= 1 - inner_thr
    return idx[keep], len(pairs) / len(run)


def matmul_intersections(masks: torch.Tensor) -> torch.Tensor:
    """A vectorised PyTorch intersection count: one (half/float) matmul of the flattened masks."""
    dt = torch.float16 if masks.is_cuda else torch.float32
    a = masks.flatten(1).to(dt)
    if masks.is_cuda:  # fp16 sums are exact only below 2048 per product: accumulate in fp32 chunks
        out = torch.zeros(a.shape[0], a.shape[0], device=a.device, dtype=torch.float64)
        for s in range(0, a.shape[1], 1 << 20):
            blk = a[:, s : s + (1 << 20)]
            out += (blk @ blk.T).double()
        return out.round().long()
    return (a @ a.T).round().long()


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
    # mask NMS at the working resolution
    for mm in ([100, 300, 1000] if cuda else [60, 200]):
        masks = blob_masks(mm, h, w, dev)
        scores = torch.rand(mm, generator=torch.Generator().manual_seed(1)).to(dev) * 0.3 + 0.7
        keep_ref = None
        t_op = median_time(lambda: mask_nms(masks, scores), repeats=3, cuda=cuda)
        keep = mask_nms(masks, scores)
        budget = 400 if cuda else 60
        (keep_ls, factor), t_ls = timed(lambda: langsplat_mask_nms(masks, scores, max_pairs=budget), dev)
        if factor == 1.0:
            keep_ref = keep_ls
        t_ls *= factor
        t_mm = median_time(lambda: matmul_intersections(masks), repeats=3, cuda=cuda)
        exact = bool(torch.equal(matmul_intersections(masks), mask_intersections(masks)))
        same = "n/a (extrapolated)" if keep_ref is None else str(keep.tolist() == keep_ref.tolist())
        rows.append({"op": f"mask NMS M={mm}", "impl": "tiger::mask_nms", "size": f"{h}x{w}", "seconds": t_op,
                     "rel_err_vs_f64": 0.0, "note": f"same keep as LangSplat: {same}"})
        rows.append({"op": f"mask NMS M={mm}", "impl": "LangSplat python loop", "size": f"{h}x{w}",
                     "seconds": t_ls, "rel_err_vs_f64": 0.0,
                     "note": f"speed-up {t_ls / t_op:.0f}x" + (" (extrapolated)" if factor > 1 else "")})
        rows.append({"op": f"mask NMS M={mm}", "impl": "torch matmul counts only", "size": f"{h}x{w}",
                     "seconds": t_mm, "rel_err_vs_f64": 0.0, "note": f"counts exact: {exact}"})
    boxes = masks_to_boxes(blob_masks(1000, h // 4, w // 4, dev)).float()
    sc = torch.rand(1000, device=dev)
    rows.append({"op": "box NMS M=1000", "impl": "tiger::box_nms", "size": "", "seconds":
                 median_time(lambda: box_nms(boxes, sc, 0.7), repeats=5, cuda=cuda), "rel_err_vs_f64": 0.0,
                 "note": ""})
    return rows


def build_models(kind: str, dev: torch.device, dtype: torch.dtype):
    from tiger.models.random_init import clip_config, random_sam, write_byte_level_clip_tokenizer
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


def bench_pipeline(dev, kind, dtype, img_hw, out_hw, clip_long, steps, n_views, points_per_batch) -> list[dict]:
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

    lenient = SamMaskConfig(points_per_batch=points_per_batch, pred_iou_thresh=-1e9, stability_score_thresh=0.0)
    gen = SamMaskGenerator(sam_model, lenient)
    gen.predict(image, (64, 64))  # warm-up
    pixels, _ = gen.preprocess(image)
    _, t_enc = timed(lambda: sam_model.get_image_embeddings(pixels.to(dtype)), dev)
    (masks, iou, stab), t_pred = timed(lambda: gen.predict(image, out_hw), dev)
    row("SAM encoder (ViT)", t_enc, f"{sam_model.config.vision_config.num_hidden_layers} blocks, {dtype}")
    row("SAM 32x32 prompts + upscale", t_pred - t_enc, f"{masks.shape[0]} masks (filters off: worst case)")
    keep, t_box = timed(lambda: box_nms(masks_to_boxes(masks), iou, 0.7), dev)
    masks, iou, stab = masks[keep], iou[keep], stab[keep]
    row("box NMS", t_box, f"{masks.shape[0]} kept")
    (masks, changed), t_clean = timed(lambda: gen._clean(masks), dev)
    row("small-region clean-up", t_clean, f"{int(changed.sum())} changed")
    keep, t_mnms = timed(lambda: mask_nms(masks, iou * stab, 0.8, -1e9, 0.5), dev)
    row("mask NMS", t_mnms, f"{masks.shape[0]} -> {keep.numel()} masks")
    sm = SamMasks(masks[keep], iou[keep], stab[keep])
    ids, t_ids = timed(lambda: sm.id_map().reshape(-1), dev)
    feats = F.normalize(hr.float(), dim=0).permute(1, 2, 0).reshape(-1, d)
    (_, means, counts), t_ma = timed(lambda: masked_average(feats, ids, sm.masks.shape[0]), dev)
    row("id map + masked average", t_ids + t_ma, f"{sm.masks.shape[0]} masks")
    acc = StreamingPCA(d, min(64, d))
    _, t_pca = timed(lambda: acc.update(torch.cat([means, feats[ids < 0]]),
                                        torch.cat([counts.float(), torch.ones(int((ids < 0).sum()), device=dev)])), dev)
    row("PCA statistics", t_pca)
    total_fast = sum(r["seconds/image"] for r in rows if r["stage"] != "FeatUp implicit")
    total_quality = sum(r["seconds/image"] for r in rows if r["stage"] != "FeatUp JBU")
    if steps > 0:
        row("TOTAL (implicit, paper)", total_quality)
    row("TOTAL (JBU, fast)", total_fast)
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
    ap.add_argument("--skip-ops", action="store_true")
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
    if not args.skip_ops:
        print_table(bench_ops(dev, *out_hw), "ops (median seconds; errors vs float64)")
    if not args.skip_pipeline:
        steps = args.steps if args.steps is not None else (1200 if cuda else 10)
        rows = bench_pipeline(dev, kind, dtype, (ih, iw), out_hw, args.clip_long_side or (448 if cuda else 224),
                              steps, args.views or (3000 if cuda else 20), 256 if cuda else 64)
        print_table(rows, f"per-image stage times ({kind} models, {dtype})")


if __name__ == "__main__":
    main()
