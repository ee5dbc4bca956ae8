"""SAM automatic-mask settings and the PCA dimension, pinned by behaviour at the defaults.

Values written from LangSplat's preprocess.py (``SamAutomaticMaskGenerator(points_per_side=32,
pred_iou_thresh=0.7, box_nms_thresh=0.7, stability_score_thresh=0.85, ...,
min_mask_region_area=100)`` and ``masks_update(..., iou_thr=0.8, score_thr=0.7, inner_thr=0.5)``),
SAM's automatic_mask_generator.py (``iou_preds > pred_iou_thresh``, ``stability_score >=
stability_score_thresh``, stability offset 1.0, mask threshold 0.0, ``remove_small_regions`` for
holes and islands) and SPEC §4 / the paper (PCA to 64 dimensions); never imported from tiger.

A stub SAM returns hand-made masks, each built so that the default and nearby values disagree.
"""
from types import SimpleNamespace

import numpy as np
import torch

from tiger.language.sam_masks import SamMaskConfig, SamMaskGenerator

POINTS_PER_SIDE = 32
PRED_IOU = 0.7
STABILITY = 0.85
BOX_NMS = 0.7
MIN_AREA = 100
MASK_NMS_IOU = 0.8
MASK_NMS_SCORE = 0.7
PCA_DIM = 64

S = 160  # the stub's input size; low-res logits are S x S, so no resampling blurs them


def _rect(y0, x0, h, w):
    m = np.zeros((S, S), bool)
    m[y0:y0 + h, x0:x0 + w] = True
    return m


def _with_ring(mask, stability):
    """Logits: 1.05 inside, 0.95 on the last pixels (raster order) so that the share of pixels
    above +1 among those above -1 (SAM's stability, offset 1) is ``stability``; -2 outside.
    An offset of 0.9 or 1.1 would give 1 or 0."""
    logits = np.where(mask, 1.05, -2.0)
    ys, xs = np.nonzero(mask)
    ring = int(round(len(ys) * (1 - stability)))
    if ring:
        logits[ys[-ring:], xs[-ring:]] = 0.95
    return logits


def programmed_masks():
    """(name, mask, predicted IoU, stability) per point prompt, and the names that must survive."""
    p = []
    # predicted IoU: 0.705 passes "> 0.7", 0.695 does not
    p += [("iou_pass", _rect(98, 0, 15, 15), 0.705, 1.0), ("iou_fail", _rect(98, 20, 15, 15), 0.695, 1.0)]
    # stability: 0.86 passes ">= 0.85", 0.84 does not
    p += [("stab_pass", _rect(98, 40, 10, 20), 0.9, 0.86), ("stab_fail", _rect(98, 65, 10, 20), 0.9, 0.84)]
    # box NMS: 20 x 61 boxes shifted by 10 px (box IoU 50/70 = 0.714 > 0.7: the lower one goes)
    # and by 11 px (49/71 = 0.690: both stay); their mask IoUs stay under 0.8
    p += [("box_a", _rect(0, 0, 20, 61), 0.9, 1.0), ("box_b", _rect(0, 10, 20, 61), 0.85, 1.0)]
    p += [("box_c", _rect(25, 80, 20, 61), 0.9, 1.0), ("box_d", _rect(25, 91, 20, 61), 0.85, 1.0)]
    # minimum area: 98 px is dropped, 102 px kept; a 9-px hole is filled
    p += [("area_98", _rect(115, 0, 7, 14), 0.9, 1.0), ("area_102", _rect(125, 0, 6, 17), 0.9, 1.0)]
    holed = _rect(115, 40, 30, 30)
    holed[125:128, 50:53] = False
    p += [("holed", holed, 0.9, 1.0)]
    # mask NMS IoU: a 20x20 square and the same square with a 1-px tail (box IoU < 0.2):
    # tail 88 px -> mask IoU 400/488 = 0.820 (the lower one goes), 113 px -> 0.780 (both stay)
    sq1, sq2 = _rect(50, 0, 20, 20), _rect(75, 0, 20, 20)
    t1, t2 = sq1.copy(), sq2.copy()
    t1[60, 20:20 + 88] = True
    t2[85, 20:20 + 113] = True
    p += [("nms_tail", t1, 0.9, 1.0), ("nms_square", sq1, 0.85, 1.0)]
    p += [("keep_tail", t2, 0.9, 1.0), ("keep_square", sq2, 0.85, 1.0)]
    # mask NMS score (IoU x stability > 0.7): 0.75 x 0.90 = 0.675 goes, 0.78 x 0.92 = 0.718 stays
    p += [("score_fail", _rect(100, 90, 10, 20), 0.75, 0.90), ("score_pass", _rect(100, 115, 10, 20), 0.78, 0.92)]
    # nested pair: a 25 x 40 mask and its top 11 rows (44 % of it): the part goes
    p += [("whole", _rect(115, 80, 25, 40), 0.9, 1.0), ("part", _rect(115, 80, 11, 40), 0.95, 1.0)]
    survivors = {"iou_pass", "stab_pass", "box_a", "box_c", "box_d", "area_102", "holed", "nms_tail",
                 "keep_tail", "keep_square", "score_pass", "whole"}
    return p, survivors


class StubSam(torch.nn.Module):
    """Enough of ``transformers.SamModel`` for SamMaskGenerator: the k-th point prompt gets the
    k-th programmed mask (multimask level 0), later prompts an IoU of 0."""

    def __init__(self, programmed):
        super().__init__()
        self.weight = torch.nn.Parameter(torch.zeros(1))
        self.config = SimpleNamespace(vision_config=SimpleNamespace(image_size=S))
        self.programmed = programmed
        self.points: list = []

    def get_image_embeddings(self, pixels):
        return torch.zeros(1, 1, 4, 4)

    def forward(self, image_embeddings, input_points, input_labels, multimask_output):
        b = input_points.shape[1]
        start = len(self.points)
        self.points.extend(input_points[0, :, 0].tolist())
        iou = torch.zeros(1, b, 3)
        logits = torch.full((1, b, 3, S, S), -2.0)
        for k in range(b):
            if start + k < len(self.programmed):
                _, mask, pred_iou, stab = self.programmed[start + k]
                iou[0, k, 0] = pred_iou
                logits[0, k, 0] = torch.from_numpy(_with_ring(mask, stab))
        return SimpleNamespace(iou_scores=iou, pred_masks=logits)


class StubDecoder:
    """The generator's prompt decoder over StubSam's forward (the level-0 mask of each prompt)."""

    def __init__(self, stub: StubSam):
        self.stub = stub

    def prepare(self, emb):
        return emb

    def __call__(self, emb, points):
        p = points.shape[0]
        out = self.stub(emb, points[None, :, None, :], torch.ones(1, p, 1), multimask_output=True)
        return out.pred_masks[0, :, 0].float(), out.iou_scores[0, :, 0]


def _generator(stub: StubSam) -> SamMaskGenerator:
    # batching does not change the masks; the stub has no decoder config to size batches from
    return SamMaskGenerator(stub, SamMaskConfig(points_per_batch=64), decoder=StubDecoder(stub))


def test_sam_defaults_on_programmed_masks():
    programmed, survivors = programmed_masks()
    stub = StubSam(programmed)
    out = _generator(stub)(torch.rand(3, S, S))
    # the point grid: 32 x 32 cell centres (SAM's build_point_grid), x fastest, in input pixels
    side = (np.arange(POINTS_PER_SIDE) + 0.5) / POINTS_PER_SIDE * S
    grid = np.stack([np.tile(side, POINTS_PER_SIDE), np.repeat(side, POINTS_PER_SIDE)], 1)
    np.testing.assert_allclose(np.asarray(stub.points), grid, atol=1e-4)
    # SAM's filters alone (before any NMS): predicted IoU > 0.7 and stability >= 0.85
    raw, iou, stab = _generator(StubSam(programmed)).predict(torch.rand(3, S, S))
    passed = {name for name, m, _, _ in programmed if any(np.array_equal(r, m) for r in raw.numpy())}
    assert passed == {name for name, _, i, s in programmed if i > PRED_IOU and s >= STABILITY}
    assert len(raw) == len(passed)
    want = {name: m for name, m, _, _ in programmed if name in survivors}
    want["holed"] = _rect(115, 40, 30, 30)  # its 9-px hole filled
    got = [m.numpy() for m in out.masks]
    matched = {name for name, m in want.items() if any(np.array_equal(g, m) for g in got)}
    assert matched == set(want), f"missing {set(want) - matched}"
    assert len(got) == len(want), f"{len(got)} masks kept, expected {sorted(want)}"


def test_pca_dimension_is_64():
    from tiger.cli.main import build_parser
    from tiger.language.extract import FeatureConfig
    from tiger.language.pca import StreamingPCA

    x = torch.randn(300, 96, generator=torch.Generator().manual_seed(0))
    acc = StreamingPCA(96)
    acc.update(x)
    assert tuple(acc.fit().components.shape) == (96, PCA_DIM)
    assert FeatureConfig().pca_dim == PCA_DIM
    assert build_parser().parse_args(["features", "images", "--out", "o"]).pca_dim == PCA_DIM
