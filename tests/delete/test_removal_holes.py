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


def _cube_on_plane(seed=3):
    """A plane (y = 0, brown) with a cardboard cube standing on it; no view sees the cube's bottom
    face or the plane under it (language feature 0). Returns means, colours, labels (0 plane,
    1 cube), language norms and the scores of "plane" and of "cube" as a trained field gives them
    (the plane's language bleeds into the cube's lowest band: mid scores there)."""
    g = torch.Generator().manual_seed(seed)
    plane = torch.cat([(torch.rand(2500, 1, generator=g) - 0.5), torch.zeros(2500, 1),
                       (torch.rand(2500, 1, generator=g) - 0.5)], 1)
    n = 1800
    face = torch.randint(0, 6, (n,), generator=g)
    u = torch.rand(n, 3, generator=g) - 0.5
    u[torch.arange(n), face % 3] = torch.where(face < 3, 0.5, -0.5)
    cube = u * 0.2 + torch.tensor([0.1, -0.1, 0.1])  # bottom face (face 1: +y) on the plane
    means = torch.cat([plane, cube])
    labels = torch.cat([torch.zeros(2500, dtype=torch.long), torch.ones(n, dtype=torch.long)])
    brown, cardboard = torch.tensor([0.55, 0.36, 0.2]), torch.tensor([0.78, 0.6, 0.35])
    colors = torch.cat([brown.expand(2500, 3), cardboard.expand(n, 3)])
    colors = (colors * (1 + 0.06 * torch.randn(len(means), 1, generator=g))).clamp(0, 1)
    under = (labels == 0) & ((means[:, [0, 2]] - torch.tensor([0.1, 0.1])).abs() <= 0.1).all(1)
    bottom = (labels == 1) & (means[:, 1] > -1e-6)
    unseen = under | bottom
    norms = torch.where(unseen, 0.0, 1.0)
    band = (labels == 1) & ~bottom & (means[:, 1] > -0.03)  # the cube's lowest band: blended
    noise = 0.03 * torch.randn(len(means), generator=g)
    plane_s = torch.where(labels == 0, 0.9, torch.where(band, 0.3, -0.7)) + noise
    cube_s = torch.where(labels == 1, 0.9, 0.05) + noise
    plane_s[unseen], cube_s[unseen] = 0.0, 0.0  # the cosine of a zero feature
    return means, colors, labels, norms, plane_s, cube_s, unseen


def test_deleting_the_support_keeps_what_stands_on_it():
    """The floater, unseen and appearance rules grow a compact object into the parts its language
    missed; for the plane a cube stands on (the table under the mug), the plane's box holds the
    whole cube, the cube's unseen bottom, its blended lowest band and a colour near the plane's:
    none of it may go with the plane."""
    means, colors, labels, norms, plane_s, _, unseen = _cube_on_plane()
    cube = labels == 1
    r = removal_mask(plane_s, plane_s > 0.5, means, 0.5, lang_norms=norms, colors=colors)
    assert int((r.mask & cube & ~unseen).sum()) == 0, r.counts()  # nothing of the cube that is seen
    assert int((r.mask & cube).sum()) <= 0.05 * int((cube & unseen).sum()), r.counts()
    assert bool(r.mask[(labels == 0) & ~unseen].all())  # the plane goes, all that is seen of it


def test_deleting_the_object_on_the_support_takes_all_of_it():
    """The same cube deleted: all of it goes, its unseen bottom included; of the plane at most
    what is under it."""
    means, colors, labels, norms, _, cube_s, unseen = _cube_on_plane()
    cube = labels == 1
    r = removal_mask(cube_s, cube_s > 0.5, means, 0.5, lang_norms=norms, colors=colors)
    assert bool(r.mask[cube].all()), int((cube & ~r.mask).sum())
    assert not bool(r.mask[(labels == 0) & ~unseen].any())  # the plane around it stays
