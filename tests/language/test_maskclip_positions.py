"""MaskCLIP's position-table resampling follows FeatUp's rule exactly.

FeatUp (featup/featurizers/maskclip/interpolate.py, after DINO): ``F.interpolate(table,
scale_factor=((g_h + 0.1) / side, (g_w + 0.1) / side), mode="bicubic", align_corners=False,
recompute_scale_factor=False)``. The reference below computes that by hand: output pixel i samples
the source at ``(i + 0.5) / scale - 0.5`` with Keys' cubic kernel (a = -0.75, PyTorch's), taps
clamped to the border.
"""
import math

import numpy as np
import torch


def cubic_weights(t: float, a: float = -0.75) -> list:
    def k(x):
        x = abs(x)
        if x <= 1:
            return (a + 2) * x ** 3 - (a + 3) * x ** 2 + 1
        if x < 2:
            return a * x ** 3 - 5 * a * x ** 2 + 8 * a * x - 4 * a
        return 0.0
    return [k(t + 1), k(t), k(1 - t), k(2 - t)]


def resample_matrix(n_out: int, side: int, scale: float) -> np.ndarray:
    """[n_out, side] weights of PyTorch's bicubic resampling at a given scale factor."""
    m = np.zeros((n_out, side))
    for i in range(n_out):
        x = (i + 0.5) / scale - 0.5
        x0 = math.floor(x)
        for tap, w in zip(range(x0 - 1, x0 + 3), cubic_weights(x - x0)):
            m[i, min(max(tap, 0), side - 1)] += w
    return m


def featup_reference(table: np.ndarray, gh: int, gw: int) -> np.ndarray:
    side = int(round(math.sqrt(table.shape[0] - 1)))
    grid = table[1:].reshape(side, side, -1)
    rows = resample_matrix(gh, side, (gh + 0.1) / side)
    cols = resample_matrix(gw, side, (gw + 0.1) / side)
    out = np.einsum("ia,jb,abd->ijd", rows, cols, grid).reshape(gh * gw, -1)
    return np.concatenate([table[:1], out], 0)


def test_hand_computed_small_case():
    # side 2 -> 3: scale 3.1 / 2 = 1.55; output 0 samples x = 0.5 / 1.55 - 0.5 = -0.17742
    m = resample_matrix(3, 2, 3.1 / 2)
    t = 0.5 / 1.55 - 0.5 - math.floor(0.5 / 1.55 - 0.5)  # 0.82258
    w = cubic_weights(t)
    np.testing.assert_allclose(m[0], [w[0] + w[1] + w[2], w[3]], atol=1e-15)
    assert abs(m[0, 1] - w[3]) < 1e-15 and abs(m[0].sum() - 1) < 1e-12
    # the size rule (scale 3/2) samples elsewhere
    assert np.abs(resample_matrix(3, 2, 3 / 2) - m).max() > 1e-3


def test_position_embeddings_follow_featup(maskclip):
    table = maskclip.clip.vision_model.embeddings.position_embedding.weight.detach().double().numpy()
    side = int(round(math.sqrt(table.shape[0] - 1)))
    for gh, gw in [(3, 5), (side + 3, 2 * side), (1, side)]:
        got = maskclip.position_embeddings(gh, gw).detach().double().numpy()
        want = featup_reference(table, gh, gw)
        np.testing.assert_allclose(got, want, atol=1e-5, rtol=1e-5)
        # interpolating to the target size instead would differ
        size_rule = torch.nn.functional.interpolate(
            torch.from_numpy(table[1:]).reshape(1, side, side, -1).permute(0, 3, 1, 2), size=(gh, gw),
            mode="bicubic", align_corners=False).permute(0, 2, 3, 1).reshape(gh * gw, -1).numpy()
        assert np.abs(size_rule - want[1:]).max() > 1e-4
    np.testing.assert_array_equal(maskclip.position_embeddings(side, side).detach().numpy(),
                                  table.astype(np.float32))
