"""The LERF localization metric on hand-made labels and maps with known hits and misses."""
from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from tiger.eval import lerf
from tiger.eval.filters import argmax_points, majority_smooth, mean_filter, reflect101_index
from tiger.eval.polygon import polygon_mask


def brute_mean_filter(x: np.ndarray, k: int) -> np.ndarray:
    """Direct definition: window rows y - k//2 .. y + k - 1 - k//2, BORDER_REFLECT_101."""
    h, w = x.shape
    a = k // 2

    def refl(i: int, n: int) -> int:
        if n == 1:
            return 0
        p = 2 * (n - 1)
        i %= p
        return p - i if i >= n else i

    out = np.zeros((h, w))
    for y in range(h):
        for xx in range(w):
            out[y, xx] = sum(x[refl(y + i - a, h), refl(xx + j - a, w)] for i in range(k) for j in range(k)) / k**2
    return out


def brute_majority(mask: np.ndarray, s: int = 3) -> np.ndarray:
    """LangSplat's loop, verbatim semantics (np.bincount argmax; exclusive H-1 / W-1 bounds)."""
    h, w = mask.shape
    out = mask.copy()
    for i in range(h):
        for j in range(w):
            sq = mask[max(0, i - s):min(i + s + 1, h - 1), max(0, j - s):min(j + s + 1, w - 1)]
            if sq.size:
                out[i, j] = np.argmax(np.bincount(sq.reshape(-1)))
    return out


@pytest.mark.parametrize("shape,k", [((13, 17), 30), ((9, 11), 4), ((6, 5), 3), ((1, 7), 30), ((40, 33), 30), ((8, 8), 1)])
def test_mean_filter_matches_definition(shape, k):
    x = np.random.default_rng(k).random(shape)
    np.testing.assert_allclose(mean_filter(torch.tensor(x), k).numpy(), brute_mean_filter(x, k), atol=1e-11)


def test_mean_filter_matches_opencv_when_available():
    cv2 = pytest.importorskip("cv2")
    rng = np.random.default_rng(0)
    for shape in [(50, 70), (31, 29), (4, 90)]:
        x = rng.random(shape).astype(np.float32)
        ref = cv2.filter2D(x, -1, np.ones((30, 30)) / 900.0)
        np.testing.assert_allclose(mean_filter(torch.tensor(x), 30).numpy(), ref, atol=3e-7)


def test_reflect101_index():
    assert reflect101_index(4, 3, 3).tolist() == [3, 2, 1, 0, 1, 2, 3, 2, 1, 0]
    assert reflect101_index(3, 5, 0).tolist() == [1, 0, 1, 2, 1, 0, 1, 2]  # ...|abc| repeated
    assert reflect101_index(1, 2, 2).tolist() == [0, 0, 0, 0, 0]


def test_majority_smooth_matches_langsplat_loop():
    rng = np.random.default_rng(1)
    for shape in [(20, 25), (7, 9), (2, 3), (1, 5)]:
        m = (rng.random(shape) > 0.45).astype(np.uint8)
        got = majority_smooth(torch.tensor(m)).numpy().astype(np.uint8)
        np.testing.assert_array_equal(got, brute_majority(m))


def test_polygon_mask_hand_made():
    # Axis-aligned rectangle: OpenCV fills the outline inclusively.
    m = polygon_mask(8, 10, [[2, 1], [6, 1], [6, 4], [2, 4]])
    want = np.zeros((8, 10), bool)
    want[1:5, 2:7] = True
    np.testing.assert_array_equal(m, want)
    # Float vertices are truncated like np.asarray(..., dtype=np.int32).
    np.testing.assert_array_equal(polygon_mask(8, 10, [[2.9, 1.7], [6.2, 1.1], [6.99, 4.5], [2.5, 4.0]]), want)
    # A right triangle: row y holds x in [1, 1 + (y - 1)].
    t = polygon_mask(6, 6, [[1, 1], [5, 5], [1, 5]])
    for y in range(6):
        row = np.nonzero(t[y])[0].tolist()
        assert row == (list(range(1, y + 1)) if y >= 1 else []), (y, row)
    assert not polygon_mask(4, 4, []).any()


def test_polygon_mask_matches_opencv_when_available():
    cv2 = pytest.importorskip("cv2")
    rng = np.random.default_rng(2)
    for _ in range(100):
        poly = rng.uniform(0, 59.99, (rng.integers(3, 12), 2))
        ref = np.zeros((60, 80), np.uint8)
        cv2.fillPoly(ref, [np.asarray(poly, dtype=np.int32)], 1)
        np.testing.assert_array_equal(polygon_mask(60, 80, poly.tolist()), ref.astype(bool))


def write_label(path, name, w, h, objects):
    path.write_text(json.dumps({"info": {"name": name, "width": w, "height": h}, "objects": objects}))


def box_obj(cat, x1, y1, x2, y2):
    return {"category": cat, "bbox": [x1, y1, x2, y2],
            "segmentation": [[x1, y1], [x2, y1], [x2, y2], [x1, y2]]}


def test_labels_merge_instances(tmp_path):
    write_label(tmp_path / "frame_00007.json", "frame_00007.jpg", 40, 30,
                [box_obj("cup", 1, 1, 5, 5), box_obj("cup", 30, 20, 35, 25), box_obj("plate", 10, 10, 20, 20)])
    fr = lerf.load_frame_labels(tmp_path / "frame_00007.json")
    assert fr.name == "frame_00007" and fr.index == 6 and (fr.height, fr.width) == (30, 40)
    assert list(fr.categories) == ["cup", "plate"]
    cup = fr.categories["cup"]
    assert cup.boxes.shape == (2, 4)
    assert cup.mask.sum() == 25 + 36 and cup.mask[3, 3] and cup.mask[22, 32] and not cup.mask[15, 15]


def test_label_errors_name_file_and_field(tmp_path):
    p = tmp_path / "frame_00001.json"
    p.write_text(json.dumps({"objects": []}))
    with pytest.raises(ValueError, match="frame_00001.json: missing field 'info'"):
        lerf.load_frame_labels(p)
    write_label(p, "frame_00001.jpg", 10, 10, [{"category": "a", "bbox": [1, 2, 3]}])
    with pytest.raises(ValueError, match=r"objects\[0\]\.bbox"):
        lerf.load_frame_labels(p)
    write_label(p, "frame_00001.jpg", 10, 10, [{"bbox": [1, 2, 3, 4]}])
    with pytest.raises(ValueError, match=r"missing field 'category' in objects\[0\]"):
        lerf.load_frame_labels(p)
    p.write_text("{not json")
    with pytest.raises(ValueError, match="not valid JSON"):
        lerf.load_frame_labels(p)
    (tmp_path / "empty").mkdir()
    with pytest.raises(FileNotFoundError, match="no label files"):
        lerf.load_scene_labels(tmp_path / "empty")
    with pytest.raises(FileNotFoundError, match="does not exist"):
        lerf.load_scene_labels(tmp_path / "nowhere")


def blob(h, w, cx, cy, r, value=1.0):
    y, x = torch.meshgrid(torch.arange(h), torch.arange(w), indexing="ij")
    return value * ((x - cx) ** 2 + (y - cy) ** 2 <= r * r).double()


def test_localization_hits_misses_and_smoothing():
    h, w = 80, 100
    # A broad bump at (70, 40) and a single very bright pixel at (10, 10): the raw maximum is the
    # spike, the 30x30 mean puts the maximum on the bump (LERF's reason for the filter).
    m = 0.2 * blob(h, w, 70, 40, 12)
    m[10, 10] = 5.0
    pts, smoothed = lerf.localize(m)
    assert lerf.points_in_boxes(pts, np.array([[55, 25, 85, 55]]))
    assert not lerf.points_in_boxes(pts, np.array([[0, 0, 20, 20]]))
    assert int(torch.argmax(m)) == 10 * w + 10
    # Merged instances: a hit on the second box of the category counts.
    assert lerf.points_in_boxes(pts, np.array([[0, 0, 20, 20], [60, 30, 80, 50]]))


def test_ties_every_maximum_counts():
    # A constant map: every pixel ties, so any box containing any pixel is a hit.
    pts, _ = lerf.localize(torch.full((20, 30), 0.7))
    assert pts.shape == (600, 2)
    assert lerf.points_in_boxes(pts, np.array([[29, 19, 29, 19]]))  # a 1-pixel box in the corner
    # Two equal plateaus far apart: two tie groups, a box around either is a hit.
    m = blob(60, 200, 30, 30, 10) + blob(60, 200, 170, 30, 10)
    pts, _ = lerf.localize(m)
    xs = pts[:, 0]
    assert (xs < 100).any() and (xs > 100).any()
    assert lerf.points_in_boxes(pts, np.array([[160, 20, 180, 40]]))
    assert lerf.points_in_boxes(pts, np.array([[20, 20, 40, 40]]))
    assert not lerf.points_in_boxes(pts, np.array([[90, 0, 110, 59]]))


def test_boxes_at_the_border_and_inclusive_bounds():
    h, w = 50, 60
    m = torch.zeros(h, w)
    m[:, -3:] = 1.0  # brightest at the right edge: the reflected border keeps it there
    pts, _ = lerf.localize(m)
    assert pts[:, 0].min() >= w - 20
    assert lerf.points_in_boxes(pts, np.array([[w - 1, 0, w - 1, h - 1]])) == bool((pts[:, 0] == w - 1).any())
    # Inclusive bounds and reversed corners.
    p = torch.tensor([[5, 7]])
    assert lerf.points_in_boxes(p, np.array([[5, 7, 9, 9]]))
    assert lerf.points_in_boxes(p, np.array([[9, 9, 5, 7]]))
    assert not lerf.points_in_boxes(p, np.array([[5.5, 7, 9, 9]]))
    assert not lerf.points_in_boxes(torch.zeros(0, 2), np.array([[0, 0, 9, 9]]))


def test_miou_variant_on_a_known_mask():
    h, w = 60, 80
    gt = np.zeros((h, w), bool)
    gt[10:40, 20:60] = True
    m = torch.zeros(h, w, dtype=torch.float64)
    m[10:40, 20:60] = 1.0
    pred = lerf.langsplat_mask(m, thresh=0.4)
    iou = lerf.mask_iou(pred, gt)
    assert 0.6 < iou <= 1.0
    # The same computed by the definition with numpy + the LangSplat loop.
    v = 0.5 * (brute_mean_filter(m.numpy(), 30) + m.numpy())
    v = v - v.min()
    v = np.clip(v / (v.max() + 1e-9) * 2 - 1, 0, 1)
    ref = brute_majority((v > 0.4).astype(np.uint8)).astype(bool)
    np.testing.assert_array_equal(pred.numpy(), ref)
    assert iou == pytest.approx((ref & gt).sum() / (ref | gt).sum())
    assert lerf.mask_iou(torch.zeros(h, w, dtype=torch.bool), np.zeros((h, w), bool)) == 0.0


def test_evaluate_scene_counts_and_table(tmp_path):
    h, w = 60, 80
    write_label(tmp_path / "frame_00001.json", "frame_00001.jpg", w, h,
                [box_obj("cup", 5, 5, 25, 25), box_obj("bear", 50, 30, 75, 55), box_obj("cup", 40, 0, 45, 5)])
    write_label(tmp_path / "frame_00002.json", "frame_00002.jpg", w, h, [box_obj("bear", 0, 0, 10, 10)])
    labels = lerf.load_scene_labels(tmp_path)
    maps = {("frame_00001", "cup"): blob(h, w, 15, 15, 8),     # hit
            ("frame_00001", "bear"): blob(h, w, 15, 45, 8),    # miss
            ("frame_00002", "bear"): blob(h, w, 70, 50, 8)}    # miss

    def fn(fr, cats):
        return torch.stack([maps[(fr.name, c)] for c in cats])

    out = tmp_path / "out"
    res = lerf.evaluate_scene("toy", labels, fn, out_dir=out, progress=False)
    assert [(q.frame, q.category, q.hit) for q in res.queries] == [
        ("frame_00001", "cup", True), ("frame_00001", "bear", False), ("frame_00002", "bear", False)]
    assert res.accuracy == pytest.approx(1 / 3)
    assert (out / "toy" / "frame_00001" / "cup.png").stat().st_size > 1000
    res2 = lerf.SceneResult("other", [lerf.QueryResult("f", "c", True, [], 1.0, 0.5)])
    table = lerf.format_table([res, res2])
    assert "| toy | 3 | 1 | 33.3 |" in table and "**66.7**" in table  # mean over scenes, not queries
    j, t = lerf.write_results([res, res2], out)
    data = json.loads(j.read_text())
    assert data["mean_accuracy"] == pytest.approx((1 / 3 + 1) / 2)
    # A wrong map count is a clear error.
    with pytest.raises(ValueError, match="expected \\[Q, H, W\\]"):
        lerf.evaluate_scene("bad", labels, lambda fr, cats: torch.zeros(5, h, w), progress=False)
