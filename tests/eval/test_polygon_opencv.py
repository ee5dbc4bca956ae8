"""Ground-truth masks equal LangSplat's ``cv2.fillPoly`` for every polygon, vertices outside the
frame included (LangSplat eval/utils.py: ``cv2.fillPoly(mask, [np.asarray(points, np.int32)], 1)``)."""
import numpy as np

from tiger.eval.polygon import polygon_mask


def langsplat_polygon_to_mask(img_shape, points_list):
    import cv2

    points = np.asarray(points_list, dtype=np.int32)
    mask = np.zeros(img_shape, dtype=np.uint8)
    cv2.fillPoly(mask, [points], 1)
    return mask


def test_random_polygons_reaching_outside_the_frame():
    rng = np.random.default_rng(7)
    h, w = 60, 80
    for k in range(300):
        n = int(rng.integers(3, 12))
        lo, hi = (-40.0, 120.0) if k % 2 else (-5.0, 85.0)  # far out, and just over the border
        poly = rng.uniform(lo, hi, (n, 2)) * np.array([1.0, h / w])
        want = langsplat_polygon_to_mask((h, w), poly.tolist()).astype(bool)
        np.testing.assert_array_equal(polygon_mask(h, w, poly.tolist()), want)


def test_float_vertices_truncate_like_int32():
    poly = [[-0.7, -3.9], [30.6, 2.2], [25.99, 40.5], [-12.5, 20.0]]
    want = langsplat_polygon_to_mask((32, 32), poly).astype(bool)
    np.testing.assert_array_equal(polygon_mask(32, 32, poly), want)
    assert want.any()
