"""Synthetic SAM-like mask sets, the baselines the mask NMS is measured against, and the
per-image SAM mask path's stage table.

    python -m benchmarks.masks --device cuda --models full          # H100: 1080x1920, 100/300/1000 masks
    python -m benchmarks.masks --device cpu --models tiny --image 270x480 --mask-counts 100,300
    python -m benchmarks.masks --device cuda --dtype float32 --agreement --profile masks_profile.txt

``realistic_masks`` builds what SAM's 32x32 automatic prompts hand to the mask stages of one
image: segments of a partition of the frame (adjacent, no overlap), near-duplicates of them (the
same segment found from neighbouring prompts: a boundary one to four pixels off, IoU 0.6-0.98),
parts of segments (nested, 20-70 % of the area) and unions of two neighbouring segments (a mask
that contains two others). Scores are SAM's predicted IoU x stability, both above SAM's filters
(IoU > 0.7, stability >= 0.85), so a few fall under LangSplat's score threshold 0.7. Every rule of
LangSplat's mask NMS fires on such a set.

Baselines (all exact, none extrapolated):
  * ``langsplat_loop``: LangSplat's ``mask_nms`` (preprocess.py) as written: a Python loop over
    the M (M + 1) / 2 pairs, with its three data-dependent ``if``s (three host syncs per pair on
    a GPU).
  * ``pairwise_loop``: the same pairwise algorithm with one host read per pair (intersection and
    union fetched together, the rules evaluated on the host).
  * ``matmul_counts``: the intersection counts as one matrix product of the flattened masks, in
    float32 (exact: 0/1 products, float32 sums exact below 2^24 pixels), TF32 or int8.
"""
from __future__ import annotations

import argparse
import math
import os
import time
from pathlib import Path

import torch
import torch.nn.functional as F


def _decide(iou_m, inner_m, scores, iou_thr, score_thr, inner_thr):
    """LangSplat's final step on its [M, M] IoU and nested-pair matrices (score order)."""
    iou_m = iou_m.triu(diagonal=1)
    keep = (iou_m.max(0).values <= iou_thr) & (scores > score_thr)
    keep &= torch.triu(inner_m, diagonal=1).max(0).values <= 1 - inner_thr
    keep &= torch.tril(inner_m, diagonal=1).max(0).values <= 1 - inner_thr
    return keep


def langsplat_loop(masks: torch.Tensor, scores: torch.Tensor, iou_thr: float = 0.8,
                   score_thr: float = 0.7, inner_thr: float = 0.5) -> torch.Tensor:
    """LangSplat's mask NMS, pair by pair as in its repository; kept indices [K] by score."""
    scores, idx = scores.sort(dim=0, descending=True, stable=True)
    n = idx.shape[0]
    mo = masks[idx]
    area = mo.sum((1, 2), dtype=torch.float)
    iou_m = torch.zeros(n, n, device=masks.device)
    inner_m = torch.zeros(n, n, device=masks.device)
    for i in range(n):
        for j in range(i, n):
            inter = torch.sum(torch.logical_and(mo[i], mo[j]), dtype=torch.float)
            union = torch.sum(torch.logical_or(mo[i], mo[j]), dtype=torch.float)
            iou_m[i, j] = inter / union
            if inter / area[i] < 0.5 and inter / area[j] >= 0.85:
                inner_m[i, j] = 1 - (inter / area[j]) * (inter / area[i])
            if inter / area[i] >= 0.85 and inter / area[j] < 0.5:
                inner_m[j, i] = 1 - (inter / area[j]) * (inter / area[i])
    return idx[_decide(iou_m, inner_m, scores, iou_thr, score_thr, inner_thr)]


def pairwise_loop(masks: torch.Tensor, scores: torch.Tensor, iou_thr: float = 0.8,
                  score_thr: float = 0.7, inner_thr: float = 0.5) -> torch.Tensor:
    """The same pairwise algorithm with one host read per pair (float32 ratios as LangSplat's)."""
    scores, idx = scores.sort(dim=0, descending=True, stable=True)
    n = idx.shape[0]
    mo = masks[idx]
    area = mo.sum((1, 2), dtype=torch.float).cpu()
    iou_m = torch.zeros(n, n)
    inner_m = torch.zeros(n, n)
    for i in range(n):
        for j in range(i, n):
            pair = torch.stack([torch.sum(torch.logical_and(mo[i], mo[j]), dtype=torch.float),
                                torch.sum(torch.logical_or(mo[i], mo[j]), dtype=torch.float)]).cpu()
            inter, union = pair[0], pair[1]
            iou_m[i, j] = inter / union
            ri, rj = inter / area[i], inter / area[j]
            if ri < 0.5 and rj >= 0.85:
                inner_m[i, j] = 1 - rj * ri
            if ri >= 0.85 and rj < 0.5:
                inner_m[j, i] = 1 - rj * ri
    return idx[_decide(iou_m, inner_m, scores.cpu(), iou_thr, score_thr, inner_thr).to(idx.device)]


def matmul_counts(masks: torch.Tensor, kind: str = "float32", chunk: int = 1 << 20) -> torch.Tensor:
    """Pairwise intersection counts [M, M] int64 as matrix products of the flattened masks.

    kind: 'float32' (TF32 off), 'tf32' (TF32 on: 0/1 inputs are exact in TF32 and the sums are
    accumulated in float32), or 'int8' (``torch._int_mm``, int32 sums; CUDA, padded to its
    shape rules). Pixels are taken ``chunk`` at a time to bound the float32 copy.
    """
    m = masks.shape[0]
    flat = masks.reshape(m, -1)
    if kind == "int8":
        mp, lp = max(24, -(-m // 8) * 8), -(-flat.shape[1] // 8) * 8
        a = torch.zeros(mp, lp, dtype=torch.int8, device=masks.device)
        a[:m, : flat.shape[1]] = flat.view(torch.int8)
        return torch._int_mm(a, a.t())[:m, :m].long()
    prev = torch.backends.cuda.matmul.allow_tf32
    torch.backends.cuda.matmul.allow_tf32 = kind == "tf32"
    try:
        out = torch.zeros(m, m, dtype=torch.float32, device=masks.device)
        for s in range(0, flat.shape[1], chunk):
            blk = flat[:, s : s + chunk].float()
            out += blk @ blk.T  # partial sums < 2^24: exact
        return out.long()
    finally:
        torch.backends.cuda.matmul.allow_tf32 = prev


def _partition(h: int, w: int, cells: int, g: torch.Generator, device) -> torch.Tensor:
    """[h, w] int64 labels of an irregular partition: nearest of ``cells`` seeds under a random
    per-seed metric, computed at 1/4 resolution and upsampled (blocky edges are fine for NMS)."""
    hl, wl = max(1, h // 4), max(1, w // 4)
    seeds = torch.rand(cells, 2, generator=g) * torch.tensor([hl, wl])
    stretch = 0.5 + torch.rand(cells, 2, generator=g)  # elongated segments of varied size
    weight = 0.4 + 1.2 * torch.rand(cells, generator=g)
    yy, xx = torch.meshgrid(torch.arange(hl, dtype=torch.float32), torch.arange(wl, dtype=torch.float32),
                            indexing="ij")
    pix = torch.stack([yy.reshape(-1), xx.reshape(-1)], 1).to(device)
    seeds, stretch, weight = seeds.to(device), stretch.to(device), weight.to(device)
    labels = torch.empty(pix.shape[0], dtype=torch.int64, device=device)
    for s in range(0, pix.shape[0], 1 << 14):
        d = ((pix[s : s + (1 << 14), None, :] - seeds[None]) * stretch[None]).square().sum(-1)
        labels[s : s + (1 << 14)] = (d * weight[None]).argmin(1)
    low = labels.view(1, 1, hl, wl).float()
    return F.interpolate(low, size=(h, w), mode="nearest")[0, 0].long()


def _grow(m: torch.Tensor, r: int) -> torch.Tensor:
    """Dilate (r > 0) or erode (r < 0) masks [K, H, W] by |r| pixels (square structuring element)."""
    x = m.to(torch.float16)[:, None]
    k = 2 * abs(r) + 1
    if r > 0:
        return F.max_pool2d(x, k, 1, abs(r))[:, 0] > 0.5
    return -F.max_pool2d(-x, k, 1, abs(r))[:, 0] > 0.5


def realistic_masks(m: int, h: int, w: int, device="cpu", seed: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
    """(masks [m, h, w] bool, scores [m]): a SAM-like mask set (see the module docstring):
    about 55 % segments, 25 % near-duplicates, 12 % parts and 8 % unions, in random order."""
    g = torch.Generator().manual_seed(seed)
    n_dup, n_part, n_union = round(0.25 * m), round(0.12 * m), round(0.08 * m)
    n_seg = m - n_dup - n_part - n_union
    labels = _partition(h, w, max(2, math.ceil(1.3 * n_seg)), g, device)
    present = torch.unique(labels).cpu()
    if len(present) < n_seg:  # a small frame has fewer segments: more duplicates instead
        n_dup, n_seg = n_dup + n_seg - len(present), len(present)
    chosen = present[torch.randperm(len(present), generator=g)[:n_seg]]
    seg = labels[None] == chosen.to(device)[:, None, None]
    out = [seg]
    if n_dup:
        src = seg[torch.randint(0, n_seg, (n_dup,), generator=g).to(device)]
        grown = torch.empty_like(src)
        radii = torch.randint(1, 5, (n_dup,), generator=g) * (torch.randint(0, 2, (n_dup,), generator=g) * 2 - 1)
        for r in radii.unique().tolist():
            sel = (radii == r).nonzero().flatten().to(device)
            grown[sel] = _grow(src[sel], int(r))
        gone = ~grown.flatten(1).any(1)  # a small segment eroded away: SAM returns no empty masks
        grown[gone] = src[gone]
        out.append(grown)
    if n_part:
        src = seg[torch.randint(0, n_seg, (n_part,), generator=g).to(device)]
        yy = torch.arange(h, device=device, dtype=torch.float32).view(1, h, 1)
        xx = torch.arange(w, device=device, dtype=torch.float32).view(1, 1, w)
        area = src.sum((1, 2)).clamp_min(1).float()
        cy = (src * yy).sum((1, 2)) / area
        cx = (src * xx).sum((1, 2)) / area
        ang = (torch.rand(n_part, generator=g) * 2 * math.pi).to(device)
        proj = (yy - cy.view(-1, 1, 1)) * torch.sin(ang).view(-1, 1, 1) + (xx - cx.view(-1, 1, 1)) * torch.cos(ang).view(-1, 1, 1)
        frac = (0.2 + 0.5 * torch.rand(n_part, generator=g)).to(device)  # kept share of the area
        vals = torch.where(src, proj, torch.full_like(proj, float("inf"))).flatten(1)
        k = (frac * area).long().clamp(1, h * w)
        cut = vals.sort(1).values.gather(1, (k - 1).view(-1, 1)).view(-1, 1, 1)
        out.append(src & (proj <= cut))
    if n_union:
        a = torch.randint(0, n_seg, (n_union,), generator=g).to(device)
        near = _grow(seg[a], 3)  # touches its neighbours
        slot = torch.full((int(labels.max()) + 1,), -1, dtype=torch.int64, device=device)
        slot[chosen.to(device)] = torch.arange(n_seg, device=device)
        b = torch.empty_like(a)
        for k in range(n_union):
            cand = slot[labels[near[k]].unique()]
            cand = cand[(cand >= 0) & (cand != a[k])]
            b[k] = cand[0] if len(cand) else (a[k] + 1) % n_seg
        out.append(seg[a] | seg[b])
    masks = torch.cat(out)[torch.randperm(m, generator=g).to(device)]
    iou = 0.7 + 0.3 * torch.rand(m, generator=g) ** 0.5
    stab = 0.85 + 0.15 * torch.rand(m, generator=g) ** 0.5
    return masks, (iou * stab).to(device)


# ---------------------------------------------------------------------------------------------
# The per-image mask path, stage by stage.


def _timed(fn, dev: torch.device, repeats: int):
    """(result of the last call, median seconds over ``repeats`` calls after one warm-up)."""
    def once():
        if dev.type == "cuda":
            torch.cuda.synchronize(dev)
        t = time.perf_counter()
        out = fn()
        if dev.type == "cuda":
            torch.cuda.synchronize(dev)
        return out, time.perf_counter() - t

    out, _ = once()
    times = []
    for _ in range(repeats):
        out, t = once()
        times.append(t)
    return out, sorted(times)[len(times) // 2]


def _decode_with_sam_model(gen, emb: torch.Tensor, resized: tuple[int, int], batch: int = 256):
    """The prompt grid through ``transformers.SamModel`` as the generator decoded it before
    SamGridDecoder: (logits [P, 256, 256] float32, iou [P]) of the generator's level."""
    from tiger.language.sam_masks import point_grid

    cfg = gen.config
    pts = point_grid(cfg.points_per_side) * torch.tensor([resized[1], resized[0]], dtype=torch.float64)
    pts = pts.to(emb.device, torch.float32)
    lows, ious = [], []
    with torch.no_grad():
        for i in range(0, pts.shape[0], batch):
            p = pts[i : i + batch]
            out = gen.model(image_embeddings=emb, input_points=p[None, :, None, :],
                            input_labels=torch.ones(1, p.shape[0], 1, dtype=torch.int64, device=emb.device),
                            multimask_output=True)
            ious.append(out.iou_scores[0, :, cfg.level].float())
            lows.append(out.pred_masks[0, :, cfg.level].float())
    return torch.cat(lows), torch.cat(ious)


def mask_agreement(dev: torch.device, kind: str, image_hw: tuple[int, int], seed: int = 0) -> list[dict]:
    """How far the bf16-autocast decoder's masks are from float32's (float32 SAM, random weights,
    every prompt kept): share of equal pixels, mask IoU (mean, min), predicted-IoU difference, and
    the masks each run keeps after SAM's filters (IoU > 0.7 is off: random weights predict ~0)."""
    from tiger.language.sam_masks import SamMaskConfig, SamMaskGenerator
    from tiger.testing.random_models import random_sam

    with torch.device(dev):
        model = random_sam(kind, seed=seed).float()
    h, w = image_hw
    image = torch.rand(3, h, w, generator=torch.Generator().manual_seed(seed)).to(dev)
    out = {}
    for bf16 in (False, True):
        gen = SamMaskGenerator(model, SamMaskConfig(pred_iou_thresh=-1e9, stability_score_thresh=0.0,
                                                    decoder_bf16=bf16, precision="fp32"))
        emb, resized = gen.embed(image)
        low, iou = gen.decode(emb, resized)
        masks, _, stab = gen.select(low, iou, resized, (h, w))
        out[bf16] = (low, iou, masks, stab)
    (l32, i32, m32, s32), (l16, i16, m16, s16) = out[False], out[True]
    inter = (m32 & m16).flatten(1).sum(1).float()
    union = (m32 | m16).flatten(1).sum(1).float()
    miou = torch.where(union > 0, inter / union.clamp_min(1), torch.ones_like(union))
    row = {"SAM": kind, "prompts": int(m32.shape[0]), "pixel agreement": float((m32 == m16).float().mean()),
           "mask IoU mean": float(miou.mean()), "mask IoU min": float(miou.min()),
           "max |logit diff| / max |logit|": float((l16 - l32).abs().max() / l32.abs().max().clamp_min(1e-30)),
           "max |pred IoU diff|": float((i16 - i32).abs().max()),
           "stability >= 0.85 (fp32 / bf16)": f"{int((s32 >= 0.85).sum())} / {int((s16 >= 0.85).sum())}"}
    print("  agreement:", row, flush=True)
    return [row]


def bench_mask_path(dev: torch.device, kind: str, dtype: torch.dtype, image_hw: tuple[int, int],
                    counts: list[int], feature_dim: int, repeats: int, baseline_max: int,
                    decoder_bf16: bool = False, compare_decoders: bool = True) -> list[dict]:
    """Seconds per image of each stage of SamMaskGenerator on ``dev`` (full or tiny random SAM),
    the mask stages on SAM-like sets of ``counts`` masks at the image size; with
    ``compare_decoders`` also the prompt decoding through transformers' SamModel (the path before)."""
    from tiger.language.sam_masks import (SamMaskConfig, SamMaskGenerator, SamMasks, clean_masks_on_host,
                                          masks_to_boxes)
    from tiger.ops.components import remove_small_regions
    from tiger.ops.masked_average import masked_average
    from tiger.ops.nms import box_nms, mask_nms
    from tiger.testing.random_models import random_sam

    rows: list[dict] = []

    def row(masks: str, stage: str, seconds: float, note: str = "") -> None:
        rows.append({"masks": masks, "stage": stage, "seconds": seconds, "note": note})
        print(f"  [{masks}] {stage}: {seconds:.4f} s  {note}", flush=True)  # partial results survive a time-out

    with torch.device(dev):
        model = random_sam(kind).to(dtype)
    h, w = image_hw
    image = torch.rand(3, h, w, generator=torch.Generator().manual_seed(0)).to(dev)
    gen_off = SamMaskGenerator(model, SamMaskConfig(pred_iou_thresh=-1e9, stability_score_thresh=0.0,
                                                    decoder_bf16=decoder_bf16, precision="fp32"))
    (emb, resized), t_enc = _timed(lambda: gen_off.embed(image), dev, repeats)
    (low, piou), t_dec = _timed(lambda: gen_off.decode(emb, resized), dev, repeats)
    (pm, _, _), t_up = _timed(lambda: gen_off.select(low, piou, resized, (h, w)), dev, repeats)
    row("-", "SAM encoder", t_enc, f"{kind} ViT, {dtype}")
    row("-", "prompt decoding (SamGridDecoder)", t_dec, f"{low.shape[0]} prompts, {gen_off._batch()} per batch"
        + (", bf16 autocast" if decoder_bf16 else ""))
    if compare_decoders:
        (ref_low, ref_iou), t_ref = _timed(lambda: _decode_with_sam_model(gen_off, emb, resized), dev, repeats)
        scale = float(ref_low.abs().max())
        row("-", "  before: transformers SamModel, 256 per batch", t_ref,
            f"max |logit diff| {float((low - ref_low).abs().max()):.2e} of {scale:.2e}, "
            f"max |IoU diff| {float((piou - ref_iou).abs().max()):.2e}")
        del ref_low
    row("-", "filters + upscale + stability", t_up, f"{pm.shape[0]} masks to {h}x{w} (random weights, filters "
        "off: every prompt upscaled, an upper bound)")
    shared = t_enc + t_dec + t_up
    del pm
    cfg = SamMaskConfig(precision="fp32")
    gen = SamMaskGenerator(model, cfg)
    feats = F.normalize(torch.randn(h * w, feature_dim, device=dev), dim=1)
    for mm in counts:
        tag = str(mm)
        masks, scores = realistic_masks(mm, h, w, dev, seed=mm)
        # realistic masks are clean: SAM's own have specks and pinholes for the clean-up to find
        # pinholes inside and specks within 3 px outside (SAM's are near the mask: boxes stay tight)
        near = torch.cat([_grow(masks[i : i + 64], 3) for i in range(0, mm, 64)]).view(-1)
        flip = torch.randint(0, mm * h * w, (400 * mm,), generator=torch.Generator().manual_seed(mm)).to(dev)
        flat = masks.view(-1)
        flat[flip] = flat[flip] ^ near[flip]
        del near
        iou, stab = scores, torch.ones_like(scores)
        keep, t_box = _timed(lambda: box_nms(masks_to_boxes(masks), iou, cfg.box_nms_thresh), dev, repeats)
        m1, i1, s1 = masks[keep], iou[keep], stab[keep]
        row(tag, "box NMS (+ boxes)", t_box, f"{mm} -> {m1.shape[0]}")
        (m2, changed), t_clean = _timed(lambda: gen._clean(m1), dev, repeats)
        row(tag, "small-region clean-up (as the generator runs it)", t_clean,
            f"{int(changed.sum())} of {m1.shape[0]} changed; " + ("tiger::remove_small_regions" if dev.type == "cuda"
                                                                 else "OpenCV per mask, threads"))
        (m2_op, _), t_op = _timed(lambda: remove_small_regions(m1, cfg.min_mask_region_area), dev, repeats)
        row(tag, "  tiger::remove_small_regions", t_op, f"same masks: {bool(torch.equal(m2_op, m2))}")
        if m1.shape[0] <= baseline_max:
            (ref, _), t_ref = _timed(lambda: clean_masks_on_host(m1, cfg.min_mask_region_area), dev, 1)
            row(tag, "  SAM's per-mask clean-up on the host (OpenCV, threads)", t_ref,
                f"same masks: {bool(torch.equal(ref, m2))}")
        assert torch.equal(m2_op, m2), f"clean-up of {mm} masks: the op differs from the generator's path"

        def second_nms():
            k = box_nms(masks_to_boxes(m2), (~changed).float(), cfg.box_nms_thresh)
            a, b, c = m2[k], i1[k], s1[k]
            big = torch.nonzero(a.flatten(1).sum(1) >= cfg.min_mask_region_area).squeeze(1)
            return a[big], b[big], c[big]

        (m3, i3, s3), t_box2 = _timed(second_nms, dev, repeats)
        row(tag, "box NMS of changed masks + area filter", t_box2, f"-> {m3.shape[0]}")
        keep, t_mnms = _timed(lambda: mask_nms(m3, i3 * s3, cfg.mask_nms_iou, cfg.mask_nms_score,
                                               cfg.mask_nms_inner), dev, repeats)
        row(tag, "mask NMS", t_mnms, f"-> {keep.numel()}")
        sm = SamMasks(m3[keep], i3[keep], s3[keep])
        ids, t_ids = _timed(lambda: sm.id_map().reshape(-1), dev, repeats)
        row(tag, "id map", t_ids, f"{100 * float((ids >= 0).float().mean()):.0f} % of pixels in a mask")
        _, t_ma = _timed(lambda: masked_average(feats, ids, sm.masks.shape[0]), dev, repeats)
        row(tag, "masked average", t_ma, f"{h * w} px x {feature_dim} channels")
        out, t_post = _timed(lambda: gen.postprocess(masks, iou, stab), dev, repeats)
        assert torch.equal(out.masks, sm.masks), "postprocess differs from its stages"
        row(tag, "postprocess as the generator runs it (box NMS .. mask NMS)", t_post)
        total = shared + t_post + t_ids + t_ma
        row(tag, "TOTAL per image (SAM + mask stages + id map + masked average)", total)
        del masks, m1, m2, m3, sm, ids, out
        if dev.type == "cuda":
            torch.cuda.empty_cache()
    return rows


def profile_generator(dev: torch.device, kind: str, dtype: torch.dtype, image_hw: tuple[int, int], path: Path,
                      decoder_bf16: bool = False) -> None:
    """torch.profiler table (by self device time on CUDA, self CPU time elsewhere) of one
    SamMaskGenerator call on a random image, SAM's filters off so every prompt reaches every stage."""
    from tiger.language.sam_masks import SamMaskConfig, SamMaskGenerator
    from tiger.testing.random_models import random_sam

    with torch.device(dev):
        model = random_sam(kind).to(dtype)
    gen = SamMaskGenerator(model, SamMaskConfig(pred_iou_thresh=-1e9, stability_score_thresh=0.0,
                                                decoder_bf16=decoder_bf16, precision="fp32"))
    image = torch.rand(3, *image_hw, generator=torch.Generator().manual_seed(0)).to(dev)
    gen(image)  # warm-up
    acts = [torch.profiler.ProfilerActivity.CPU] + ([torch.profiler.ProfilerActivity.CUDA] if dev.type == "cuda" else [])
    with torch.profiler.profile(activities=acts) as prof:
        gen(image)
        if dev.type == "cuda":
            torch.cuda.synchronize(dev)
    key = "self_cuda_time_total" if dev.type == "cuda" else "self_cpu_time_total"
    path.write_text(prof.key_averages().table(sort_by=key, row_limit=40))
    print(f"profile of one generator call -> {path}")


def main() -> None:
    from benchmarks.common import print_table

    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    ap.add_argument("--models", choices=["tiny", "full"], default=None, help="random SAM size (default: full on "
                    "CUDA, tiny on CPU)")
    ap.add_argument("--image", default="1080x1920", help="HxW of the image and the masks")
    ap.add_argument("--mask-counts", default="100,300,1000", help="SAM-like mask set sizes")
    ap.add_argument("--feature-dim", type=int, default=512, help="channels of the masked average's map (CLIP: 512)")
    ap.add_argument("--repeats", type=int, default=None, help="timed calls per stage (median; default 5 CUDA, 1 CPU)")
    ap.add_argument("--baseline-max", type=int, default=400,
                    help="run SAM's per-mask host clean-up (the previous path) up to this many masks")
    ap.add_argument("--dtype", choices=("bfloat16", "float32"), default=None,
                    help="SAM's weights (default bfloat16 on CUDA, float32 on CPU; `tiger features` loads "
                         "float32; random full-size weights overflow float16)")
    ap.add_argument("--decoder-bf16", action="store_true", help="time the prompt decoder under bf16 autocast")
    ap.add_argument("--no-compare", action="store_true",
                    help="skip timing transformers' SamModel decoder (the path before SamGridDecoder)")
    ap.add_argument("--agreement", action="store_true",
                    help="also measure the bf16-autocast decoder's masks against float32's (float32 SAM)")
    ap.add_argument("--profile", type=Path, default=None, metavar="FILE",
                    help="write a torch.profiler table of one whole generator call (300-mask image) to FILE")
    args = ap.parse_args()
    dev = torch.device(args.device)
    cuda = dev.type == "cuda"
    kind = args.models or ("full" if cuda else "tiny")
    dtype = getattr(torch, args.dtype) if args.dtype else (torch.bfloat16 if cuda else torch.float32)
    ih, iw = (int(v) for v in args.image.split("x"))
    counts = [int(c) for c in args.mask_counts.split(",")]
    print(f"device {dev} ({torch.cuda.get_device_name(dev) if cuda else f'{os.cpu_count()} CPU threads'}), "
          f"SAM {kind}, image {ih}x{iw}")
    rows = bench_mask_path(dev, kind, dtype, (ih, iw), counts, args.feature_dim,
                           args.repeats or (5 if cuda else 1), args.baseline_max, args.decoder_bf16,
                           not args.no_compare)
    print_table(rows, f"per-image SAM mask path, seconds ({kind} SAM, {dtype}, {ih}x{iw})")
    if args.agreement:
        print_table(mask_agreement(dev, kind, (ih, iw)), "bf16-autocast prompt decoder vs float32 (float32 SAM)")
    if args.profile:
        profile_generator(dev, kind, dtype, (ih, iw), args.profile, args.decoder_bf16)


if __name__ == "__main__":
    main()
