"""SPEC §8 stress set: no NaN/Inf out of any output or gradient; clear errors on bad input."""
from __future__ import annotations

import math

import pytest
import torch

import tiger
from tiger.render.reference import render_ref

from .scenes import camera, random_scene

F64 = torch.float64


def _render_and_grads(means, quats, scales, opac, colors, V, K, w, h, **kw):
    # The kernels must stay finite also on what the input checks refuse (a zero quaternion).
    kw.setdefault("check_finite", False)
    leaves = [t.detach().clone().requires_grad_() for t in (means, quats, scales, opac, colors, V, K)]
    out = tiger.rasterize_gaussians(*leaves, w, h, **kw)
    loss = out["color"].sum() + out["alpha"].sum() + out["depth"].sum()
    if loss.requires_grad:
        loss.backward()
    return out, [t.grad for t in leaves]


def _assert_finite(out, grads):
    for k in ("color", "alpha", "depth", "means2d", "conics"):
        assert bool(torch.isfinite(out[k]).all()), k
    for i, g in enumerate(grads):
        assert g is None or bool(torch.isfinite(g).all()), f"gradient {i}"
    assert bool((out["alpha"] >= 0).all()) and bool((out["alpha"] <= 1).all())


def _case(name, dtype):
    w, h = 37, 29  # not multiples of 16
    m, q, s, o, c = random_scene(120, 4, dtype=F64, seed=31)
    V, K = camera(w, h)
    if name == "degenerate_scales":
        s[:40] = 0.0
        s[40:80, 0] = 1e-9
    elif name == "huge_scales":
        s[:10] = 1e3
        s[10:20] = 1e6
    elif name == "unnormalised_quats":
        q[:40] *= 1e4
        q[40:80] *= 1e-6
        q[80] = 0.0
    elif name == "alpha_to_one":
        o[:] = 1.0
        s[:] = 0.3
    elif name == "behind_and_straddling":
        cam_z = (m @ V[:3, :3].T + V[:3, 3])[:, 2]
        eye = -V[:3, :3].T @ V[:3, 3]
        fwd = V[2, :3]
        m[:40] = eye - 0.5 * fwd + 0.1 * torch.randn(40, 3, dtype=F64)  # behind
        m[40:80] = eye + 0.011 * fwd + 0.001 * torch.randn(40, 3, dtype=F64)  # at the near plane
        s[40:80] = 0.5
        del cam_z
    elif name == "stacked_on_one_pixel":
        m = torch.zeros(3000, 3, dtype=F64)
        q = torch.randn(3000, 4, dtype=F64)
        s = torch.full((3000, 3), 0.05, dtype=F64)
        o = torch.full((3000,), 0.5, dtype=F64)
        c = torch.rand(3000, 4, dtype=F64)
    elif name == "empty":
        m, q, s, o, c = (t[:0] for t in (m, q, s, o, c))
    elif name == "one_pixel":
        w = h = 1
        V, K = camera(1, 1)
    elif name == "tiny_opacity":
        o[:] = 1e-8
    return [t.to(dtype) for t in (m, q, s, o, c, V, K)] + [w, h]


CASES = ["degenerate_scales", "huge_scales", "unnormalised_quats", "alpha_to_one",
         "behind_and_straddling", "stacked_on_one_pixel", "empty", "one_pixel", "tiny_opacity"]


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("case", CASES)
@pytest.mark.parametrize("antialiased", [False, True])
def test_stress_outputs_and_gradients_finite(case, dtype, antialiased):
    args = _case(case, dtype)
    out, grads = _render_and_grads(*args, antialiased=antialiased, sh_degree=None)
    _assert_finite(out, grads)


@pytest.mark.parametrize("case", ["alpha_to_one", "stacked_on_one_pixel", "unnormalised_quats",
                                  "degenerate_scales", "one_pixel"])
def test_stress_matches_reference(case):
    m, q, s, o, c, V, K, w, h = _case(case, F64)
    out = tiger.rasterize_gaussians(m, q, s, o, c, V, K, w, h, check_finite=False)
    ref = render_ref(m, q, s, o, c, V, K, w, h)
    for key in ("color", "alpha"):
        assert torch.allclose(out[key], ref[key], atol=1e-10), key


def test_stacked_pixel_stops_at_t_min():
    m, q, s, o, c, V, K, w, h = _case("stacked_on_one_pixel", F64)
    out = tiger.rasterize_gaussians(m, q, s, o, c, V, K, w, h, t_min=1e-4)
    # Transmittance never goes below t_min: alpha <= 1 - t_min everywhere.
    assert float(out["alpha"].max()) <= 1 - 1e-4 + 1e-12
    assert float(out["alpha"].max()) > 0.99


def test_sh_stress_finite():
    m, q, s, o, _, V, K, w, h = _case("unnormalised_quats", torch.float32)
    sh = torch.randn(m.shape[0], 16, 3) * 10
    m = m.clone()
    m[0] = -(V[:3, :3].T @ V[:3, 3])  # a Gaussian exactly at the camera centre: zero view dir
    out, grads = _render_and_grads(m, q, s, o, sh, V, K, w, h, sh_degree=3)
    _assert_finite(out, grads)


class TestBadInput:
    def _args(self):
        m, q, s, o, c = random_scene(10, 3)
        V, K = camera(16, 16)
        return [m, q, s, o, c, V, K, 16, 16]

    @pytest.mark.parametrize("idx,name,bad", [
        (0, "means", torch.zeros(10, 2, dtype=F64)),
        (1, "quats", torch.zeros(10, 3, dtype=F64)),
        (2, "scales", torch.zeros(9, 3, dtype=F64)),
        (3, "opacities", torch.zeros(10, 1, dtype=F64)),
        (4, "colors", torch.zeros(10, dtype=F64)),
        (5, "viewmat", torch.eye(3, dtype=F64)),
        (6, "K", torch.eye(4, dtype=F64)),
    ])
    def test_wrong_shape_names_tensor(self, idx, name, bad):
        args = self._args()
        args[idx] = bad
        with pytest.raises(ValueError, match=rf"{name} must have shape"):
            tiger.rasterize_gaussians(*args)

    @pytest.mark.parametrize("idx,name", [(0, "means"), (1, "quats"), (2, "scales"),
                                          (3, "opacities"), (4, "colors"), (5, "viewmat"),
                                          (6, "K")])
    @pytest.mark.parametrize("value", [math.nan, math.inf])
    def test_non_finite_names_tensor(self, idx, name, value):
        args = self._args()
        args[idx] = args[idx].clone()
        args[idx].view(-1)[0] = value
        with pytest.raises(ValueError, match=rf"{name} contains 1 non-finite"):
            tiger.rasterize_gaussians(*args)
        tiger.rasterize_gaussians(*self._args(), check_finite=False)

    @pytest.mark.parametrize("idx,name,row,value,message", [
        (1, "quats", 3, [0.0, 0.0, 0.0, 0.0], "is zero"),
        (3, "opacities", 7, 1.25, r"is outside \[0, 1\]"),
        (3, "opacities", 2, -0.01, r"is outside \[0, 1\]"),
        (2, "scales", 5, [0.1, -0.02, 0.1], "has a negative entry"),
    ])
    def test_bad_values_name_tensor_and_row(self, idx, name, row, value, message):
        args = self._args()
        args[idx] = args[idx].clone()
        args[idx][row] = torch.tensor(value, dtype=F64)
        with pytest.raises(ValueError, match=rf"{name}\[{row}\] = .*{message}.* \(1 bad row\(s\) of 10\)"):
            tiger.rasterize_gaussians(*args)
        out = tiger.rasterize_gaussians(*args, check_finite=False)  # the knob switches them off
        assert out["color"].shape == (16, 16, 3)

    def test_first_bad_row_and_count(self):
        args = self._args()
        args[3] = args[3].clone()
        args[3][[4, 8]] = 2.0
        with pytest.raises(ValueError, match=r"opacities\[4\] = 2.0 .*\(2 bad row\(s\) of 10\)"):
            tiger.rasterize_gaussians(*args)

    def test_edge_values_are_accepted(self):
        args = self._args()
        for idx, row, value in ((3, 0, 0.0), (3, 1, 1.0), (2, 2, [0.0, 0.0, 0.0]), (1, 3, [0.0, 0.0, 0.0, -2.0])):
            args[idx] = args[idx].clone()
            args[idx][row] = torch.tensor(value, dtype=F64)
        tiger.rasterize_gaussians(*args)

    @pytest.mark.parametrize("width,height", [(16.5, 16), (16, 15.9), ("16", 16), (True, 16)])
    def test_non_integer_size(self, width, height):
        args = self._args()
        with pytest.raises(TypeError, match="must be a whole number of pixels"):
            tiger.rasterize_gaussians(*args[:7], width, height)

    def test_integer_valued_sizes_are_accepted(self):
        import numpy as np

        args = self._args()
        ref = tiger.rasterize_gaussians(*args)["color"]
        for w, h in ((16.0, 16.0), (np.int64(16), torch.tensor(16))):
            assert torch.equal(tiger.rasterize_gaussians(*args[:7], w, h)["color"], ref)

    def test_dtype_mismatch(self):
        args = self._args()
        args[4] = args[4].float()
        with pytest.raises(TypeError, match="colors has dtype"):
            tiger.rasterize_gaussians(*args)

    def test_integer_tensor(self):
        args = self._args()
        args[0] = torch.zeros(10, 3, dtype=torch.int64)
        with pytest.raises(TypeError, match="means must be a floating-point"):
            tiger.rasterize_gaussians(*args)

    def test_device_mismatch(self):
        args = self._args()
        args[2] = args[2].to("meta")
        with pytest.raises(ValueError, match="scales is on meta"):
            tiger.rasterize_gaussians(*args)

    def test_bad_sizes_and_options(self):
        args = self._args()
        with pytest.raises(ValueError, match="width and height must be positive"):
            tiger.rasterize_gaussians(*args[:7], 0, 16)
        with pytest.raises(ValueError, match="sh_degree must be in"):
            tiger.rasterize_gaussians(*args, sh_degree=4)
        with pytest.raises(ValueError, match="SH coefficients"):
            tiger.rasterize_gaussians(*args[:4], torch.zeros(10, 4, 3, dtype=F64), *args[5:],
                                      sh_degree=2)
        with pytest.raises(ValueError, match="background must have shape"):
            tiger.rasterize_gaussians(*args, background=torch.zeros(4, dtype=F64))
        with pytest.raises(RuntimeError, match="alpha_max must be in"):
            tiger.rasterize_gaussians(*args, alpha_max=1.0)

    def test_op_level_errors_name_tensor(self):
        m, q, s, o, c, V, K, w, h = self._args()
        with pytest.raises(RuntimeError, match="tiger.project_gaussians: quats must have shape"):
            torch.ops.tiger.project_gaussians(m, q[:, :3], s, o, V, K, w, h, 0.3, 0.01, 1e10,
                                              1 / 255, False)
        with pytest.raises(RuntimeError, match="sh degree must be in"):
            torch.ops.tiger.sh_to_color(m, torch.zeros(10, 16, 3, dtype=F64), 5, None)
