"""The floater rule (planted floaters near and far from an object) and the hole masks."""
import pytest
import torch

from tiger.delete.holes import disk_dilate, hole_masks
from tiger.delete.removal import removal_mask


def _planted(seed=0):
    """An object (cube of side 0.4 at the origin, score ~0.85), a background (score ~0.05, some of
    it inside the object's box), floaters near the object (score 0.3-0.45) and far away ones."""
    g = torch.Generator().manual_seed(seed)
    obj = (torch.rand(500, 3, generator=g) - 0.5) * 0.4
    bg = (torch.rand(3000, 3, generator=g) - 0.5) * 4.0
    near = (torch.rand(40, 3, generator=g) - 0.5) * 0.44  # inside the box grown by 10 %
    far = (torch.rand(30, 3, generator=g) - 0.5) * 0.4 + torch.tensor([1.5, 0.0, 0.0])
    means = torch.cat([obj, bg, near, far])
    scores = torch.cat([0.85 + 0.03 * torch.randn(500, generator=g),
                        0.05 + 0.05 * torch.randn(3000, generator=g),
                        0.3 + 0.15 * torch.rand(40, generator=g),
                        0.3 + 0.15 * torch.rand(30, generator=g)])
    kind = torch.cat([torch.full((n,), k) for k, n in enumerate((500, 3000, 40, 30))])
    return means, scores, kind


def test_floater_rule_removes_near_floaters_only():
    means, scores, kind = _planted()
    tau = 0.5
    r = removal_mask(scores, scores > tau, means, tau)
    assert torch.equal(r.retrieved, kind == 0)
    assert torch.equal(r.floaters, kind == 2)  # every near floater, nothing else
    assert torch.equal(r.mask, (kind == 0) | (kind == 2))
    bg_in_box = (kind == 1) & ((means >= r.box_min) & (means <= r.box_max)).all(1)
    assert int(bg_in_box.sum()) > 0 and not bool(r.mask[bg_in_box].any())  # table under the mug stays
    med = float(scores.double().median())
    assert r.floater_tau == pytest.approx(med + 0.5 * (tau - med))
    assert r.counts() == {"retrieved": 500, "floaters": 40, "unseen": 0, "similar": 0, "stray_kept": 0, "removed": 540,
                          "total": 3570, "kept": 3030}


def test_unseen_rule_removes_hidden_gaussians_inside_the_box_only():
    means, scores, kind = _planted()
    norms = torch.ones_like(scores)
    g = torch.Generator().manual_seed(1)
    hidden_in = (torch.rand(25, 3, generator=g) - 0.5) * 0.3  # inside the object, never seen
    hidden_out = (torch.rand(25, 3, generator=g) - 0.5) * 0.3 + torch.tensor([0.0, 1.2, 0.0])
    means = torch.cat([means, hidden_in, hidden_out])
    scores = torch.cat([scores, torch.zeros(50)])  # cosine of a zero feature
    norms = torch.cat([norms, torch.zeros(25), 0.05 * torch.ones(25)])
    kind = torch.cat([kind, torch.full((25,), 4), torch.full((25,), 5)])
    r = removal_mask(scores, scores > 0.5, means, 0.5, lang_norms=norms)
    assert torch.equal(r.unseen, kind == 4)
    assert torch.equal(r.mask, (kind == 0) | (kind == 2) | (kind == 4))
    assert r.counts()["unseen"] == 25
    off = removal_mask(scores, scores > 0.5, means, 0.5)
    assert int(off.unseen.sum()) == 0


def test_appearance_rule_grows_along_the_object_not_into_its_support():
    """A white cylinder standing on a brown plane; the language field missed a band of it (scores
    like the plane's). The band is white and touches the retrieved part: removed; the brown plane
    under and around the cylinder stays, as does a white patch away from the object."""
    g = torch.Generator().manual_seed(2)
    th = torch.rand(3000, generator=g) * 6.2832
    y = -torch.rand(3000, generator=g) * 0.3  # cylinder from the plane (y=0) up to y=-0.3
    cyl = torch.stack([0.1 * torch.cos(th), y, 0.1 * torch.sin(th)], 1)
    plane = torch.cat([(torch.rand(4000, 1, generator=g) - 0.5) * 1.0, torch.zeros(4000, 1),
                       (torch.rand(4000, 1, generator=g) - 0.5) * 1.0], 1)
    patch = torch.cat([0.4 + 0.05 * torch.rand(50, 1, generator=g), torch.zeros(50, 1),
                       0.4 + 0.05 * torch.rand(50, 1, generator=g)], 1)
    means = torch.cat([cyl, plane, patch])
    white, brown = torch.tensor([0.9, 0.9, 0.88]), torch.tensor([0.55, 0.35, 0.2])
    colors = torch.cat([white.expand(3000, 3), brown.expand(4000, 3), white.expand(50, 3)])
    colors = (colors + 0.03 * torch.randn(7050, 3, generator=g)).clamp(0, 1)
    band = torch.zeros(7050, dtype=torch.bool)
    band[:3000] = (y > -0.2) & (y < -0.12)
    scores = torch.cat([torch.where(band[:3000], 0.05, 0.9), torch.full((4050,), 0.05)])
    scores = scores + 0.02 * torch.randn(7050, generator=g)
    r = removal_mask(scores, scores > 0.5, means, 0.5, colors=colors)
    assert int(band.sum()) > 400
    missed = int((~r.mask[:3000]).sum())
    assert missed <= 0.01 * int(band.sum()), missed  # the cylinder, all but a few isolated ones
    assert not bool((r.similar & ~band).any())  # the rule added band Gaussians only
    assert not bool(r.mask[3000:].any())  # the plane and the far white patch stay
    off = removal_mask(scores, scores > 0.5, means, 0.5, colors=colors, appearance_margin=None)
    assert int(off.similar.sum()) == 0 and int((band & ~off.mask).sum()) > 0


def test_floater_rule_knobs():
    means, scores, kind = _planted()
    off = removal_mask(scores, scores > 0.5, means, 0.5, floater_fraction=1.0)
    assert int(off.floaters.sum()) == 0
    strict = removal_mask(scores, scores > 0.5, means, 0.5, floater_tau=0.4)
    assert torch.equal(strict.floaters, (kind == 2) & (scores > 0.4))
    with pytest.raises(ValueError, match="selected no Gaussian"):
        removal_mask(scores, torch.zeros_like(scores, dtype=torch.bool), means, 0.5)
    with pytest.raises(ValueError, match="means must be"):
        removal_mask(scores, scores > 0.5, means[:, :2], 0.5)


def test_hole_masks_visible_and_thin_then_dilated():
    vis = torch.zeros(1, 20, 20)
    rest = torch.ones(1, 20, 20)
    vis[0, 5:10, 5:10] = 0.9   # object seen here ...
    rest[0, 5:10, 5:8] = 0.1   # ... and only these columns are thin afterwards
    rest[0, 15, 15] = 0.0      # thin but the object was not there: not a hole
    h0 = hole_masks(vis, rest, dilate=0)
    ref = torch.zeros(1, 20, 20, dtype=torch.bool)
    ref[0, 5:10, 5:8] = True
    assert torch.equal(h0, ref)
    h2 = hole_masks(vis, rest, dilate=2)
    assert torch.equal(h2, disk_dilate(ref, 2))
    # disk of radius 2 around a single pixel: 13 pixels
    one = torch.zeros(9, 9, dtype=torch.bool)
    one[4, 4] = True
    assert int(disk_dilate(one, 2).sum()) == 13
    with pytest.raises(ValueError, match="hole_masks"):
        hole_masks(vis, rest[0])
