"""Locality of an edit: the rest of the scene renders as before, and the locality metric's error
comes from the edited object's own faint edge, as it does for the exact recolour.

The edit renders frozen Gaussians first and the editable ones behind them (RenderLayout); the
edited scene keeps the frozen rows bit-identical in scene order, so every pixel no edited Gaussian
reaches (before or after the edit) must render as the original. Tolerance: 1e-5, float rounding
(the transmittance cut-off can fall on an edited Gaussian that adds nothing to a pixel's
footprint); on these scenes the difference is exactly 0.
"""
import math

import pytest
import torch

from tiger.edit import EditConfig, edit, resolve_target
from tiger.edit.views import ObjectViews
from tiger.eval.edit import PSNR_CAP, locality, locality_parts
from tiger.scene.sh import rgb_to_sh
from tiger.testing.ideal_denoiser import IdealDenoiserGuidance, render_targets

from .scenes import query_a, two_objects

REST_TOLERANCE = 1e-5
RED = (0.86, 0.08, 0.08)


def _exact_recolour(scene, mask):
    t = scene.clone()
    t.sh_dc[mask] = rgb_to_sh(torch.tensor(RED)).expand(int(mask.sum()), 3)
    t.sh_rest[mask] = 0  # view-independent, as the edit makes its Gaussians
    return t


@pytest.fixture(scope="module")
def edited():
    """The two-object scene, object A edited toward its exact recolour with the loop's defaults
    (view pool, densification: children appended, transparent editable ones pruned)."""
    scene = two_objects()
    tgt = resolve_target(scene, query_a(), tau=0.5)
    truth = _exact_recolour(scene, tgt.mask)
    white = torch.ones(3)
    cfg = EditConfig(steps=100, width=48, height=48, lrs={"sh_dc": 0.05}, densify_every=10, densify_from=10,
                     background=(1.0, 1.0, 1.0), progress=False, checkpoint_every=0)
    res = edit(scene, tgt, IdealDenoiserGuidance(render_targets(truth, white), seed=0), config=cfg)
    cams = ObjectViews(tgt.center, tgt.bbox_min, tgt.bbox_max, force_360=True, width=96, height=96).fixed(6, 15.0)
    return scene, tgt, truth, res, cams, white


def test_pixels_no_edited_gaussian_reaches_render_as_before(edited):
    scene, tgt, _, res, cams, white = edited
    assert len(res.scene) != len(scene)  # densification ran: rows were added and removed
    loc = locality(scene, res.scene, cams, tgt.mask, res.editable, background=white)
    rest = loc["parts"]["rest"]
    assert rest["pixels"] > 0.5 * loc["pixels"]  # object B and the background: most of what is compared
    assert rest["max_abs_err"] <= REST_TOLERANCE, rest
    assert rest["psnr"] == PSNR_CAP


def test_edit_is_as_local_as_the_exact_recolour(edited):
    """The metric counts the object's faint edge (coverage under 2 %, beyond 4 px) as outside, so
    the exact recolour itself scores below the cap; the edit scores as well as it (no leak of its
    own), and what it loses is in the fringe."""
    scene, tgt, truth, res, cams, white = edited
    exact = locality(scene, truth, cams, tgt.mask, tgt.mask, background=white)
    got = locality(scene, res.scene, cams, tgt.mask, res.editable, background=white)
    assert exact["psnr"] < PSNR_CAP and exact["parts"]["fringe"]["psnr"] < PSNR_CAP  # the edge is seen
    assert got["psnr"] >= exact["psnr"] - 1.0, (got["psnr"], exact["psnr"])
    assert got["parts"]["rest"]["psnr"] == PSNR_CAP


def test_locality_parts_known_answer():
    """Hand-made 1x2x3 images: one fringe pixel, one spread pixel, one changed rest pixel."""
    before = torch.zeros(1, 2, 3, 3, dtype=torch.float64)
    after = before.clone()
    after[0, 0, 0] = 0.1  # fringe: reached before
    after[0, 0, 1] = 0.2  # spread: reached only after
    after[0, 1, 2] = 0.3  # rest: reached by neither
    outside = torch.ones(1, 2, 3, dtype=torch.bool)
    outside[0, 1, 0] = False  # inside the footprint: not compared
    after[0, 1, 0] = 1.0
    reach_before = torch.zeros(1, 2, 3, dtype=torch.bool)
    reach_before[0, 0, 0] = True
    reach_after = reach_before.clone()
    reach_after[0, 0, 1] = True
    parts = locality_parts(before, after, outside, reach_before, reach_after)
    n = 5
    for name, value, pixels in (("fringe", 0.1, 1), ("spread", 0.2, 1), ("rest", 0.3, 3)):
        assert parts[name]["pixels"] == pixels
        assert parts[name]["psnr"] == pytest.approx(-10 * math.log10(value ** 2 / n), rel=1e-9)
        assert parts[name]["max_abs_err"] == pytest.approx(value)
