"""Deleting an object with the defaults removes all of it (no cap of the ball's underside left on
the table, checked in the pixels) and leaves every other object in place."""
from __future__ import annotations

import pytest
import torch

from ..retrieval.test_default_selection import trained_tabletop
from tiger.delete import DeleteConfig, delete, views_around
from tiger.retrieval import retrieve


@pytest.fixture(scope="module")
def tabletop():
    return trained_tabletop()


def _colour_share(images: torch.Tensor, where: torch.Tensor, rgb: tuple) -> float:
    """Share of the pixels ``where`` [V, H, W] whose colour is within 0.2 of ``rgb``."""
    close = (images - torch.tensor(rgb)).abs().amax(dim=-1) < 0.2
    return float((close & where).sum()) / max(int(where.sum()), 1)


@pytest.mark.parametrize("name", ["ball", "mug"])
def test_delete_removes_the_whole_object_and_nothing_else(tabletop, name):
    ls, enc = tabletop
    k = ls.names.index(name)
    obj = ls.labels == k
    r = retrieve(ls.scene, name, encoder=enc)  # the defaults
    cams = views_around(r, 4, 96, 72)
    res = delete(ls.scene, r, cams, config=DeleteConfig(steps=20), progress=False)
    removed = res.removal.mask
    assert int((obj & ~removed).sum()) <= 0.002 * int(obj.sum()), int((obj & ~removed).sum())
    others = (~obj) & (ls.labels != 0)  # the other objects: none of their Gaussians is touched
    assert int((removed & others).sum()) == 0
    # the table loses at most the Gaussians under the object's footprint
    table_removed = removed & (ls.labels == 0)
    if bool(table_removed.any()):
        lo, hi = res.removal.box_min, res.removal.box_max
        m = ls.scene.means[table_removed]
        assert bool(((m >= lo) & (m <= hi)).all())
    # pixels: where the object was seen, none of its colour is left (the ball's blue, the mug's
    # white and red band) in the renders after the deletion
    with torch.no_grad():
        seen = torch.stack([ls.scene.render(c, obj.float()[:, None].expand(-1, 3).contiguous())["color"][..., 0]
                            for c in cams]) > 0.5
    colours = {"ball": [(0.1, 0.3, 0.85), (0.95, 0.8, 0.1)], "mug": [(0.93, 0.93, 0.9), (0.85, 0.1, 0.1)]}[name]
    for rgb in colours:
        assert _colour_share(res.before, seen, rgb) > 0.05  # the colour was there
        assert _colour_share(res.after, seen, rgb) < 0.005, (name, rgb)
    # every kept Gaussian of the other objects is bit-identical and in its place
    kept = ~removed
    n_rest = int(kept.sum())
    assert torch.equal(res.scene.means[:n_rest][~res.trainable[:n_rest]],
                       ls.scene.means[kept][~res.trainable[:n_rest]])
