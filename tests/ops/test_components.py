"""tiger::connected_components and tiger::remove_small_regions against scipy.ndimage.label and
SAM's per-mask clean-up (tiger.language.sam_masks.remove_small_regions_of_mask, OpenCV or scipy)."""
import numpy as np
import pytest
import torch
from scipy import ndimage

import tiger  # noqa: F401
from tiger.language.sam_masks import remove_small_regions_of_mask as sam_remove_small_regions
from tiger.ops.components import connected_components, remove_small_regions

CUDA = torch.cuda.is_available() and tiger.ops.cuda_enabled()
EIGHT = np.ones((3, 3), dtype=bool)


def scipy_labels(mask: np.ndarray) -> np.ndarray:
    """scipy's 8-connected labels renamed to each component's first pixel (row-major), -1 outside."""
    labels, n = ndimage.label(mask, structure=EIGHT)
    flat = labels.ravel()
    first = np.full(n + 1, -1, dtype=np.int64)
    order = np.arange(flat.size)[::-1]  # the last write of a reversed scan is the first pixel
    first[flat[order]] = order
    first[0] = -1
    return first[labels].astype(np.int32)


def scipy_clean(mask: np.ndarray, area: int) -> tuple[np.ndarray, bool]:
    """SAM's holes-then-islands clean-up written with scipy.ndimage.label alone."""
    changed = False
    labels, n = ndimage.label(~mask, structure=EIGHT)
    sizes = np.bincount(labels.ravel(), minlength=n + 1)
    small = [k for k in range(1, n + 1) if sizes[k] < area]
    if small:
        mask = mask | np.isin(labels, small)
        changed = True
    labels, n = ndimage.label(mask, structure=EIGHT)
    sizes = np.bincount(labels.ravel(), minlength=n + 1)
    small = [k for k in range(1, n + 1) if sizes[k] < area]
    if small:
        changed = True
        big = [k for k in range(1, n + 1) if sizes[k] >= area]
        if not big:  # scipy numbers components in raster order of their first pixel: argmax ties agree
            big = [1 + int(np.argmax(sizes[1:]))]
        mask = np.isin(labels, big)
    return mask, changed


def structured_masks(m: int, h: int, w: int, seed: int) -> torch.Tensor:
    """Masks with holes, islands, regions touching by an edge or only by a corner, thin lines and
    a spiral (long chains across tiles), plus random blobs."""
    g = np.random.default_rng(seed)
    out = np.zeros((m, h, w), dtype=bool)
    yy, xx = np.mgrid[:h, :w]
    for k in range(m):
        mk = out[k]
        for _ in range(g.integers(1, 6)):  # discs and boxes
            cy, cx, r = g.integers(0, h), g.integers(0, w), g.integers(2, max(3, min(h, w) // 3))
            if g.random() < 0.5:
                mk |= (yy - cy) ** 2 + (xx - cx) ** 2 <= r * r
            else:
                mk[max(0, cy - r): cy + r, max(0, cx - r): cx + r] = True
        for _ in range(g.integers(0, 8)):  # holes of 1-30 px
            cy, cx, s = g.integers(0, h), g.integers(0, w), g.integers(1, 6)
            mk[cy: cy + s, cx: cx + g.integers(1, 6)] = False
        for _ in range(g.integers(0, 8)):  # islands of 1-30 px
            cy, cx, s = g.integers(0, h), g.integers(0, w), g.integers(1, 6)
            mk[cy: cy + s, cx: cx + g.integers(1, 6)] = True
        if k % 3 == 0:  # two squares touching only at a corner, a one-pixel line
            cy, cx = g.integers(5, max(6, h - 12)), g.integers(5, max(6, w - 12))
            mk[cy - 5: cy, cx - 5: cx] = True
            mk[cy: cy + 5, cx: cx + 5] = True
            mk[g.integers(0, h), :] = True
        if k % 4 == 1:  # a spiral of one-pixel walls
            t = np.linspace(0, 10 * np.pi, 20 * (h + w))
            r = t / t[-1] * min(h, w) / 2
            ys = np.clip((h / 2 + r * np.sin(t)).astype(int), 0, h - 1)
            xs = np.clip((w / 2 + r * np.cos(t)).astype(int), 0, w - 1)
            mk[ys, xs] = True
    return torch.from_numpy(out)


def random_masks(m, h, w, density, seed):
    g = torch.Generator().manual_seed(seed)
    return torch.rand(m, h, w, generator=g) < density


CASES = [(random_masks, 4, 37, 53, 0.45), (random_masks, 3, 33, 65, 0.6), (random_masks, 2, 20, 20, 0.2)]


@pytest.mark.parametrize("seed", [0, 1])
@pytest.mark.parametrize("make,m,h,w,density", CASES)
def test_labels_match_scipy(make, m, h, w, density, seed):
    masks = make(m, h, w, density, seed)
    labels = connected_components(masks)
    assert labels.dtype == torch.int32 and labels.shape == masks.shape
    for k in range(m):
        np.testing.assert_array_equal(labels[k].numpy(), scipy_labels(masks[k].numpy()))


def test_labels_structured_match_scipy():
    masks = structured_masks(8, 70, 97, seed=3)
    labels = connected_components(masks)
    for k in range(masks.shape[0]):
        np.testing.assert_array_equal(labels[k].numpy(), scipy_labels(masks[k].numpy()))


@pytest.mark.parametrize("area", [1, 10, 100])
def test_clean_matches_sam_and_scipy(area):
    masks = torch.cat([structured_masks(12, 64, 90, seed=area), random_masks(4, 64, 90, 0.55, area),
                       random_masks(2, 64, 90, 0.97, area), torch.zeros(1, 64, 90, dtype=torch.bool),
                       torch.ones(1, 64, 90, dtype=torch.bool)])
    tiny = torch.zeros(1, 64, 90, dtype=torch.bool)  # only small islands: the largest (first of equals) stays
    tiny[0, 3:5, 3:5] = True
    tiny[0, 30:32, 40:42] = True
    tiny[0, 50, 50] = True
    masks = torch.cat([masks, tiny])
    cleaned, changed = remove_small_regions(masks, area)
    assert cleaned.dtype == torch.bool and changed.shape == (masks.shape[0],)
    for k in range(masks.shape[0]):
        mk = masks[k].numpy()
        m1, c1 = sam_remove_small_regions(mk, area, "holes")
        m2, c2 = sam_remove_small_regions(m1, area, "islands")
        np.testing.assert_array_equal(cleaned[k].numpy(), m2, err_msg=f"mask {k}")
        assert bool(changed[k]) == (c1 or c2), f"mask {k}"
        ref, ref_changed = scipy_clean(mk, area)
        np.testing.assert_array_equal(cleaned[k].numpy(), ref, err_msg=f"mask {k} (scipy)")
        assert bool(changed[k]) == ref_changed
    if area == 100:
        assert cleaned[-1, 3:5, 3:5].all() and cleaned[-1].sum() == 4 and changed[-1]


def test_edge_cases_and_errors():
    empty = torch.zeros(0, 5, 7, dtype=torch.bool)
    cleaned, changed = remove_small_regions(empty, 10)
    assert cleaned.shape == (0, 5, 7) and changed.shape == (0,)
    assert connected_components(empty).shape == (0, 5, 7)
    with pytest.raises(RuntimeError, match="bool"):
        connected_components(torch.zeros(1, 4, 4))
    with pytest.raises(RuntimeError, match=r"\[M, H, W\]"):
        remove_small_regions(torch.zeros(4, 4, dtype=torch.bool), 10)
    with pytest.raises(RuntimeError, match="area_threshold"):
        remove_small_regions(torch.zeros(1, 4, 4, dtype=torch.bool), -1)


def test_opcheck():
    masks = structured_masks(3, 20, 24, seed=0)
    torch.library.opcheck(torch.ops.tiger.connected_components, (masks,))
    torch.library.opcheck(torch.ops.tiger.remove_small_regions, (masks, 10))


@pytest.mark.skipif(not CUDA, reason="needs CUDA and tiger's CUDA kernels")
@pytest.mark.parametrize("h,w", [(70, 97), (129, 250), (300, 533)])
def test_cuda_matches_cpu(h, w):
    masks = torch.cat([structured_masks(10, h, w, seed=h), random_masks(4, h, w, 0.5, h),
                       random_masks(2, h, w, 0.62, h)])  # near the percolation threshold: long chains
    labels = connected_components(masks.cuda())
    assert torch.equal(labels.cpu(), connected_components(masks))
    for area in (1, 20, 100):
        cleaned, changed = remove_small_regions(masks.cuda(), area)
        ref, ref_changed = remove_small_regions(masks, area)
        assert torch.equal(cleaned.cpu(), ref) and torch.equal(changed.cpu(), ref_changed)
    torch.library.opcheck(torch.ops.tiger.connected_components, (masks[:2].cuda(),))
    torch.library.opcheck(torch.ops.tiger.remove_small_regions, (masks[:2].cuda(), 10))


@pytest.mark.skipif(not CUDA, reason="needs CUDA and tiger's CUDA kernels")
def test_cuda_realistic_masks_match_cpu():
    from benchmarks.masks import realistic_masks

    masks, _ = realistic_masks(120, 270, 480, seed=7)
    cleaned, changed = remove_small_regions(masks.cuda(), 100)
    ref, ref_changed = remove_small_regions(masks, 100)
    assert torch.equal(cleaned.cpu(), ref) and torch.equal(changed.cpu(), ref_changed)
