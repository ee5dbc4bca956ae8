"""The LERF / LangSplat evaluation constants, pinned by behaviour at the defaults.

Written from LangSplat's eval/evaluate_iou_loc.py and eval/utils.py (the protocol TIGER's Table 1
follows), never imported from tiger:
  * localization: ``scale = 30; kernel = np.ones((scale, scale)) / scale**2;
    cv2.filter2D(relev, -1, kernel)``, then the pixel(s) of maximum value;
  * mIoU variant: ``0.5 * (filtered + relev)``, min-max normalised, ``* 2 - 1``, clipped to
    [0, 1], ``> mask_thresh`` with ``--mask_thresh`` default 0.4, then ``smooth`` (majority in
    ``mask[max(0, i-3) : min(i+3+1, h-1), ...]``, scale 3).
The reference below is that code with its constants as explicit arguments.
"""
import cv2
import numpy as np
import pytest
import torch

from tiger.eval import lerf
from tiger.eval.lerf import CategoryLabel, FrameLabels, evaluate_scene, langsplat_mask, localize

SCALE = 30
MASK_THRESH = 0.4
SMOOTH_SCALE = 3


def ref_filtered(relev: np.ndarray, scale: int) -> np.ndarray:
    return cv2.filter2D(relev, -1, np.ones((scale, scale)) / (scale ** 2))


def ref_smooth(mask: np.ndarray, scale: int) -> np.ndarray:
    h, w = mask.shape[:2]
    out = mask.copy()
    for i in range(h):
        for j in range(w):
            square = mask[max(0, i - scale): min(i + scale + 1, h - 1), max(0, j - scale): min(j + scale + 1, w - 1)]
            out[i, j] = np.argmax(np.bincount(square.reshape(-1)))
    return out


def ref_mask(relev: np.ndarray, scale: int, thresh: float, smooth_scale: int) -> np.ndarray:
    v = 0.5 * (ref_filtered(relev, scale) + relev)
    v = v - v.min()
    v = v / (v.max() + 1e-9)
    v = np.clip(v * 2.0 - 1.0, 0, 1)
    return ref_smooth((v > thresh).astype(np.uint8), smooth_scale).astype(bool)


def three_blocks() -> tuple[np.ndarray, list]:
    """Blocks of side 29 (value 1.03), 30 (1.00) and 31 (0.97): a k x k mean filter peaks on the
    29-block for k <= 29, on the 30-block only for k = 30, on the 31-block for k = 31."""
    relev = np.zeros((160, 200), np.float64)
    relev[20:49, 20:49] = 1.03
    relev[20:50, 110:140] = 1.00
    relev[100:131, 60:91] = 0.97
    box30 = [110, 20, 139, 49]
    return relev, box30


def _argmax_box(filtered: np.ndarray) -> tuple[int, int]:
    ys, xs = np.nonzero(filtered == filtered.max())
    return int(xs[0]), int(ys[0])


def test_localization_filter_is_30x30():
    relev, box = three_blocks()
    # the reference: the 30x30 filter peaks inside the 30-block; 29 and 31 do not
    inside = lambda p: box[0] <= p[0] <= box[2] and box[1] <= p[1] <= box[3]  # noqa: E731
    assert inside(_argmax_box(ref_filtered(relev, SCALE)))
    assert not inside(_argmax_box(ref_filtered(relev, SCALE - 1)))
    assert not inside(_argmax_box(ref_filtered(relev, SCALE + 1)))
    pts, smoothed = localize(torch.from_numpy(relev))
    assert all(inside(p) for p in pts.tolist())
    np.testing.assert_allclose(smoothed.numpy(), ref_filtered(relev, SCALE), atol=1e-12)


def _frame(relev: np.ndarray, box: list, gt: np.ndarray) -> FrameLabels:
    h, w = relev.shape
    return FrameLabels(name="frame_00001", index=0, height=h, width=w,
                       categories={"thing": CategoryLabel(boxes=np.asarray([box], np.float64), mask=gt)})


def _iou(a: np.ndarray, b: np.ndarray) -> float:
    u = (a | b).sum()
    return float((a & b).sum() / u) if u else 0.0


def ramp_and_lines() -> np.ndarray:
    """A plateau at 0.5 with vertical lines 3 and 4 px wide at 1.0 (7x7 majority smoothing removes
    the 3-px line and keeps the 4-px one; 5x5 keeps both, 9x9 removes both), then a ramp from 0.5
    to 1.0 (the threshold moves its edge)."""
    h, w = 72, 150
    relev = np.zeros((h, w), np.float64)
    relev[:, 10:70] = 0.5
    relev[:, 25:28] = 1.0
    relev[:, 45:49] = 1.0
    relev[:, 70:] = np.linspace(0.5, 1.0, w - 70)[None]
    return relev


def test_miou_variant_threshold_0_4_and_smoothing_7x7():
    relev = ramp_and_lines()
    want = ref_mask(relev, SCALE, MASK_THRESH, SMOOTH_SCALE)
    # the scene tells the constants apart
    for scale, thresh, sm in [(SCALE, 0.35, SMOOTH_SCALE), (SCALE, 0.45, SMOOTH_SCALE),
                              (SCALE, MASK_THRESH, 2), (SCALE, MASK_THRESH, 4), (20, MASK_THRESH, SMOOTH_SCALE)]:
        assert not np.array_equal(ref_mask(relev, scale, thresh, sm), want), (scale, thresh, sm)
    got = langsplat_mask(torch.from_numpy(relev)).numpy()
    assert np.array_equal(got, want)


def test_evaluate_scene_defaults_are_the_protocols():
    relev, box = three_blocks()
    gt = np.zeros(relev.shape, bool)
    gt[20:50, 110:140] = True
    res = evaluate_scene("s", [_frame(relev, box, gt)], lambda fr, cats: torch.from_numpy(relev)[None],
                         pictures=False, progress=False)
    q = res.queries[0]
    assert q.hit
    assert q.iou == pytest.approx(_iou(ref_mask(relev, SCALE, MASK_THRESH, SMOOTH_SCALE), gt), abs=1e-12)
    relev2 = ramp_and_lines()
    gt2 = np.zeros(relev2.shape, bool)
    gt2[:, 100:] = True
    res2 = evaluate_scene("s", [_frame(relev2, [0, 0, 1, 1], gt2)], lambda fr, cats: torch.from_numpy(relev2)[None],
                          pictures=False, progress=False)
    want = _iou(ref_mask(relev2, SCALE, MASK_THRESH, SMOOTH_SCALE), gt2)
    assert res2.queries[0].iou == pytest.approx(want, abs=1e-12)
    assert want != pytest.approx(_iou(ref_mask(relev2, SCALE, 0.45, SMOOTH_SCALE), gt2), abs=1e-6)


def test_cli_defaults_are_the_protocols():
    args = lerf.build_parser().parse_args(["--labels", "L", "--out", "O"])
    relev, box = three_blocks()
    gt = np.zeros(relev.shape, bool)
    res = evaluate_scene("s", [_frame(relev, box, gt)], lambda fr, cats: torch.from_numpy(relev)[None],
                         size=args.filter_size, mask_thresh=args.mask_thresh, pictures=False, progress=False)
    assert res.queries[0].hit
    relev2 = ramp_and_lines()
    gt2 = np.zeros(relev2.shape, bool)
    gt2[:, 100:] = True
    res2 = evaluate_scene("s", [_frame(relev2, [0, 0, 1, 1], gt2)], lambda fr, cats: torch.from_numpy(relev2)[None],
                          size=args.filter_size, mask_thresh=args.mask_thresh, pictures=False, progress=False)
    assert res2.queries[0].iou == pytest.approx(_iou(ref_mask(relev2, SCALE, MASK_THRESH, SMOOTH_SCALE), gt2),
                                                abs=1e-12)


# LangSplat eval/openclip_encoder.py (from LERF): ``self.negatives = ("object", "things", "stuff",
# "texture")``, ``softmax(10 * sims)``, the minimum over the negatives of the positive's share.
NEGATIVES = ("object", "things", "stuff", "texture")
TEMPERATURE = 10.0


class _RecordingEncoder:
    """A text encoder with a fixed random vector per text, recording what it was asked."""

    def __init__(self, dim: int) -> None:
        self.dim, self.asked, self.table = dim, [], {}

    def encode_text(self, texts):
        self.asked.extend(texts)
        for t in texts:
            g = torch.Generator().manual_seed(sum(map(ord, t)) * 7919 + len(t))
            self.table.setdefault(t, torch.randn(self.dim, generator=g))
        return torch.stack([self.table[t] for t in texts])


def test_relevancy_uses_the_canonical_negatives_and_temperature_10():
    from tiger.retrieval import retrieve

    d = 8
    feats = torch.randn(50, d, generator=torch.Generator().manual_seed(0))
    enc = _RecordingEncoder(d)
    got = retrieve(feats, "a red cup", encoder=enc, score="relevancy", tau=0.5)
    assert sorted(set(enc.asked) - {"a red cup"}) == sorted(NEGATIVES)
    unit = torch.nn.functional.normalize
    phi = unit(feats.double(), dim=1)
    cq = phi @ unit(enc.table["a red cup"].double(), dim=0)
    share = torch.stack([torch.softmax(TEMPERATURE * torch.stack([cq, phi @ unit(enc.table[n].double(), dim=0)], -1),
                                       -1)[:, 0] for n in NEGATIVES], 1)
    torch.testing.assert_close(got.relevancy.double(), share.min(1).values, atol=1e-5, rtol=1e-5)
