"""tiger::box_nms, tiger::mask_intersections and tiger::mask_nms against brute-force references."""
import pytest
import torch

import tiger  # noqa: F401
from tiger.ops.nms import box_nms, mask_intersections, mask_nms

CUDA = torch.cuda.is_available() and tiger.ops.cuda_enabled()


def greedy_nms_reference(boxes, scores, thr):
    order = sorted(range(len(scores)), key=lambda i: (-float(scores[i]), i))
    keep = []
    for i in order:
        ok = True
        for j in keep:
            a, b = boxes[i].double(), boxes[j].double()
            w = max(0.0, float(min(a[2], b[2]) - max(a[0], b[0])))
            h = max(0.0, float(min(a[3], b[3]) - max(a[1], b[1])))
            inter = w * h
            uni = float((a[2] - a[0]) * (a[3] - a[1]) + (b[2] - b[0]) * (b[3] - b[1])) - inter
            if uni > 0 and inter / uni > thr:
                ok = False
                break
        if ok:
            keep.append(i)
    return keep


def langsplat_mask_nms_reference(masks, scores, iou_thr, score_thr, inner_thr):
    """LangSplat's ``mask_nms`` written out pairwise, as in its repository."""
    scores, idx = scores.sort(dim=0, descending=True, stable=True)
    n = idx.shape[0]
    mo = masks[idx].float()
    area = mo.sum((1, 2))
    iou_m = torch.zeros(n, n, dtype=torch.float64)
    inner_m = torch.zeros(n, n, dtype=torch.float64)
    for i in range(n):
        for j in range(i, n):
            inter = float((mo[i] * mo[j]).sum())
            union = float(((mo[i] + mo[j]) > 0).sum())
            iou_m[i, j] = inter / union if union > 0 else 0.0
            ri = inter / float(area[i]) if area[i] > 0 else 0.0
            rj = inter / float(area[j]) if area[j] > 0 else 0.0
            if ri < 0.5 and rj >= 0.85:
                inner_m[i, j] = 1 - rj * ri
            if ri >= 0.85 and rj < 0.5:
                inner_m[j, i] = 1 - rj * ri
    iou_m.triu_(diagonal=1)
    iou_max = iou_m.max(0).values
    inner_u = torch.triu(inner_m, diagonal=1).max(0).values
    inner_l = torch.tril(inner_m, diagonal=1).max(0).values
    keep = (iou_max <= iou_thr) & (scores > score_thr) & (inner_u <= 1 - inner_thr) & (inner_l <= 1 - inner_thr)
    return idx[keep]


def random_boxes(n, seed):
    g = torch.Generator().manual_seed(seed)
    xy = torch.rand(n, 2, generator=g) * 50
    wh = torch.rand(n, 2, generator=g) * 30 + 0.5
    return torch.cat([xy, xy + wh], 1), torch.rand(n, generator=g)


def blob_masks(m, h, w, seed):
    """Rectangles and discs, some nested and some near-duplicates: every NMS rule fires."""
    g = torch.Generator().manual_seed(seed)
    yy, xx = torch.meshgrid(torch.arange(h), torch.arange(w), indexing="ij")
    out = []
    for k in range(m):
        cy, cx = (torch.rand(2, generator=g) * torch.tensor([h, w])).tolist()
        r = float(torch.rand((), generator=g) * min(h, w) / 3 + 1)
        if k % 3 == 0:
            out.append(((yy - cy) ** 2 + (xx - cx) ** 2) <= r * r)
        else:
            out.append(((yy - cy).abs() <= r) & ((xx - cx).abs() <= r * 0.7))
        if k % 4 == 1:  # near-duplicate of the previous one
            prev = out[-2].clone()
            prev[int(cy) % h, :] = False
            out.append(prev)
        if k % 5 == 2:  # a small mask nested in the previous one
            inner = torch.zeros(h, w, dtype=torch.bool)
            ys, xs = torch.nonzero(out[-1], as_tuple=True)
            if len(ys):
                y0, x0 = int(ys.float().mean()), int(xs.float().mean())
                inner[max(0, y0 - 2): y0 + 2, max(0, x0 - 2): x0 + 2] = True
                out.append(inner & out[-1])
    return torch.stack(out)


@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("thr", [0.3, 0.7])
def test_box_nms_matches_greedy_reference(seed, thr):
    boxes, scores = random_boxes(60, seed)
    scores[5] = scores[6]  # a tie: lower index first
    keep = box_nms(boxes, scores, thr)
    assert keep.tolist() == greedy_nms_reference(boxes, scores, thr)
    keep64 = box_nms(boxes.double(), scores.double(), thr)
    assert keep64.tolist() == keep.tolist()


def test_box_nms_edge_cases():
    assert box_nms(torch.zeros(0, 4), torch.zeros(0), 0.5).numel() == 0
    degenerate = torch.tensor([[0.0, 0, 0, 0], [0, 0, 0, 0], [1, 1, 5, 5]])
    assert box_nms(degenerate, torch.tensor([0.9, 0.8, 0.1]), 0.5).tolist() == [0, 1, 2]
    with pytest.raises(RuntimeError, match="boxes must be \\[N, 4\\]"):
        box_nms(torch.zeros(3, 3), torch.zeros(3), 0.5)
    with pytest.raises(RuntimeError, match="scores must be \\[N\\]"):
        box_nms(torch.zeros(3, 4), torch.zeros(2), 0.5)


def test_mask_intersections_match_matmul():
    masks = torch.rand(9, 13, 17) > 0.6  # 221 pixels: a partial last 64-bit word
    ref = masks.flatten(1).double() @ masks.flatten(1).double().T
    assert torch.equal(mask_intersections(masks), ref.long())
    torch.library.opcheck(torch.ops.tiger.mask_intersections, (masks,))


@pytest.mark.parametrize("seed", [0, 1])
def test_mask_nms_matches_langsplat_reference(seed):
    masks = blob_masks(14, 24, 31, seed)
    g = torch.Generator().manual_seed(seed + 10)
    scores = torch.rand(masks.shape[0], generator=g) * 0.5 + 0.5
    for iou_thr, score_thr, inner_thr in [(0.8, 0.7, 0.5), (0.5, 0.0, 0.5), (0.95, 0.6, 0.2)]:
        got = mask_nms(masks, scores, iou_thr, score_thr, inner_thr)
        ref = langsplat_mask_nms_reference(masks, scores, iou_thr, score_thr, inner_thr)
        assert got.tolist() == ref.tolist()
    # every rule is exercised: something is suppressed by overlap and by nesting
    assert len(mask_nms(masks, scores, 0.8, 0.0, 0.5)) < masks.shape[0]


def test_mask_nms_edge_cases():
    assert mask_nms(torch.zeros(0, 4, 4, dtype=torch.bool), torch.zeros(0)).numel() == 0
    empty = torch.zeros(2, 4, 4, dtype=torch.bool)
    assert mask_nms(empty, torch.tensor([0.9, 0.8])).tolist() == [0, 1]
    with pytest.raises(RuntimeError, match="masks must be bool"):
        mask_nms(torch.zeros(2, 4, 4), torch.zeros(2))


@pytest.mark.cuda
@pytest.mark.skipif(not CUDA, reason="needs CUDA and tiger's CUDA kernels")
def test_cuda_matches_cpu():
    boxes, scores = random_boxes(300, 3)
    assert box_nms(boxes.cuda(), scores.cuda(), 0.5).cpu().tolist() == box_nms(boxes, scores, 0.5).tolist()
    masks = blob_masks(70, 90, 77, 4)
    assert torch.equal(mask_intersections(masks.cuda()).cpu(), mask_intersections(masks))
    s = torch.rand(masks.shape[0]) * 0.5 + 0.5
    assert mask_nms(masks.cuda(), s.cuda()).cpu().tolist() == mask_nms(masks, s).tolist()
    torch.library.opcheck(torch.ops.tiger.mask_intersections, (masks.cuda(),))
