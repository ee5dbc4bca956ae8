"""The rasterizer's published constants, pinned by behaviour at the defaults.

Values written from INRIA's diff-gaussian-rasterization (cuda_rasterizer/forward.cu, config.h)
and SPEC §3, never imported from tiger:
  * dilation of the 2D covariance ``cov[0][0] += 0.3f`` (eps2d = 0.3 px^2),
  * ``alpha = min(0.99f, opacity * exp(power))`` (alpha_max = 0.99),
  * ``if (alpha < 1.0f / 255.0f) continue`` (alpha threshold 1/255),
  * ``test_T = T * (1 - alpha); if (test_T < 0.0001f) done`` (T_min = 1e-4),
  * ``BLOCK_X 16, BLOCK_Y 16`` (16x16 tiles).
Each scene is built so that the default and any nearby value give different outputs.
"""
import math

import torch

import tiger

EPS2D = 0.3
ALPHA_MAX = 0.99
ALPHA_THRESHOLD = 1.0 / 255.0
T_MIN = 1e-4
TILE = 16

F = 100.0  # focal length [px]
Z = 5.0  # depth of every Gaussian


def _camera(w: int, h: int):
    K = torch.tensor([[F, 0.0, w / 2], [0.0, F, h / 2], [0.0, 0.0, 1.0]], dtype=torch.float64)
    return torch.eye(4, dtype=torch.float64), K


def _render(px: list, opacities: list, w: int = 32, h: int = 32, colors=None, depths=None, **knobs):
    """Point-like Gaussians (scale 1e-7: the 2D covariance is eps2d * I) whose centres project to
    the pixel positions ``px`` [(x, y), ...], rendered with every accuracy knob at its default."""
    n = len(px)
    V, K = _camera(w, h)
    z = torch.tensor(depths if depths is not None else [Z] * n, dtype=torch.float64)
    xy = torch.tensor(px, dtype=torch.float64)
    means = torch.stack([(xy[:, 0] - w / 2) * z / F, (xy[:, 1] - h / 2) * z / F, z], 1)
    quats = torch.tensor([[1.0, 0.0, 0.0, 0.0]] * n, dtype=torch.float64)
    scales = torch.full((n, 3), 1e-7, dtype=torch.float64)
    op = torch.tensor(opacities, dtype=torch.float64)
    col = torch.ones(n, 1, dtype=torch.float64) if colors is None else torch.tensor(colors, dtype=torch.float64)
    return tiger.rasterize_gaussians(means.float(), quats.float(), scales.float(), op.float(), col.float(),
                                     V.float(), K.float(), w, h, **knobs)


def _alpha_at(opacity: float, d2: float) -> float:
    """Source formula: opacity * exp(-d^2 / (2 eps2d)) for a point-like Gaussian."""
    return opacity * math.exp(-0.5 * d2 / EPS2D)


def test_eps2d_is_0_3():
    # One Gaussian centred on pixel (10, 10); its neighbours at distance 1 and sqrt(2) see the
    # dilation alone: alpha = o exp(-d^2 / 0.6). eps2d 0.25 or 0.35 moves them by > 10 %.
    out = _render([(10.5, 10.5)], [0.8])
    img = out["color"][..., 0].double()
    assert abs(float(img[10, 10]) - 0.8) < 1e-6
    for (y, x), d2 in [((10, 11), 1.0), ((11, 11), 2.0), ((10, 12), 4.0)]:
        want = _alpha_at(0.8, d2)
        want = want if want >= ALPHA_THRESHOLD else 0.0
        assert abs(float(img[y, x]) - want) <= 1e-6 + 1e-5 * want, (y, x, float(img[y, x]), want)


def test_alpha_threshold_is_1_over_255():
    # Neighbour pixels whose alpha lies just above 1/255 (0.0042, kept: a threshold of 1/240 or
    # 1/100 drops it) and just below (0.0036, skipped: 1/300 would keep it).
    g1 = _alpha_at(1.0, 1.0)
    above, below = 0.0042 / g1, 0.0036 / g1
    out = _render([(8.5, 8.5), (24.5, 24.5)], [above, below])
    img = out["color"][..., 0].double()
    assert abs(float(img[8, 9]) - 0.0042) < 1e-6
    assert float(img[24, 25]) == 0.0
    assert abs(float(img[24, 24]) - below) < 1e-6  # the centre itself is far above the threshold


def test_alpha_max_is_0_99():
    out = _render([(16.5, 16.5)], [1.0])
    assert abs(float(out["alpha"][16, 16]) - ALPHA_MAX) < 1e-6
    assert abs(float(out["color"][16, 16, 0]) - ALPHA_MAX) < 1e-6


def test_t_min_is_1e_4():
    # Three layers of alpha 0.95 and one of 0.5 on one pixel, one channel each: T before them is
    # 1, 0.05, 2.5e-3, 1.25e-4. The third ends at T = 1.25e-4 >= 1e-4 and counts (T_min 2e-4
    # would drop it); the fourth would end at 6.25e-5 < 1e-4 and stops the pixel (T_min 5e-5 or
    # 1e-5 would keep it).
    a = 0.95
    out = _render([(5.5, 5.5)] * 4, [a, a, a, 0.5], w=12, h=12, colors=torch.eye(4).tolist(),
                  depths=[Z, Z + 1, Z + 2, Z + 3])
    px = out["color"][5, 5].double()
    want = [a, a * (1 - a), a * (1 - a) ** 2, 0.0]
    for k in range(4):
        assert abs(float(px[k]) - want[k]) < 1e-7, (k, float(px[k]), want[k])
    assert abs(float(out["alpha"][5, 5]) - (1 - (1 - a) ** 3)) < 1e-6


def test_tiles_are_16_pixels():
    # A point-like Gaussian reaches alpha >= 1/255 only within ~1.8 px of its centre. Centred on
    # the line x = 16 (y = 8) it touches pixels on both sides of a 16-px tile border: 2 tiles.
    # Centred at (24, 24), (30, 40.5) or (34, 50.5) it stays inside one 16-px tile, while tiles
    # of 8, 12, 15 or 17 px cut some of these three.
    scene = ([(16.0, 8.5), (24.0, 24.0), (30.0, 40.5), (34.0, 50.5)], [1.0] * 4)
    assert _render(*scene, w=64, h=64)["n_isects"] == 2 + 1 + 1 + 1
    # the count tells the tile size: other sizes give other counts on this scene
    counts = {t: _render(*scene, w=64, h=64, tile_size=t)["n_isects"] for t in (8, 12, 15, 17, 32)}
    assert all(c != 5 for c in counts.values()), counts
    assert _render(*scene, w=64, h=64, tile_size=TILE)["n_isects"] == 5


def test_mask_nms_op_defaults_are_langsplats():
    # LangSplat's masks_update(..., iou_thr=0.8, score_thr=0.7, inner_thr=0.5): a square and the
    # same square with a 1-px tail at mask IoU 0.820 (the lower score goes), another pair at 0.780
    # (both stay), a mask scored 0.69 (goes) and a part holding 44 % of a mask (goes).
    from tiger.ops.nms import mask_nms

    m = torch.zeros(7, 64, 160, dtype=torch.bool)
    m[0, 0:20, 0:20] = True
    m[1] = m[0]
    m[1, 10, 20:108] = True  # 400 / 488 = 0.820
    m[2, 30:50, 0:20] = True
    m[3] = m[2]
    m[3, 40, 20:133] = True  # 400 / 513 = 0.780
    m[4, 0:10, 120:140] = True
    m[5, 30:55, 140:160] = True  # 500 px
    m[6, 30:41, 140:160] = True  # its top 11 rows: 44 %
    scores = torch.tensor([0.85, 0.9, 0.85, 0.9, 0.69, 0.9, 0.95])
    for op in (lambda: mask_nms(m, scores), lambda: torch.ops.tiger.mask_nms(m, scores)):
        assert sorted(op().tolist()) == [1, 2, 3, 5]


def test_mask_nms_decides_in_float32_as_langsplat():
    # LangSplat's IoU is a float32 tensor compared with 0.8 in float32: an IoU of
    # 5,600,001 / 7,000,001 = 0.80000002857 rounds to 0.8f and passes "<= 0.8" there (in float64
    # it would not). Two nested masks of a 2048 x 4096 frame with exactly that IoU: both stay.
    from tiger.ops.nms import mask_nms

    p, q = 5_600_001, 7_000_001
    m = torch.zeros(2, 2048 * 4096, dtype=torch.bool)
    m[0, :q] = True
    m[1, :p] = True
    inter, union = torch.tensor(float(p)), torch.tensor(float(q))  # float32, as LangSplat's sums
    assert bool(inter / union <= 0.8) and p / q > 0.8
    keep = mask_nms(m.view(2, 2048, 4096), torch.tensor([0.9, 0.8]))
    assert keep.tolist() == [0, 1]
