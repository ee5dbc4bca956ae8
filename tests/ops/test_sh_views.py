"""tiger::sh_to_color over V views (dirs [V, N, 3], visible [V, N]): every view equal to its one-view
call bit for bit, the coefficient gradients the sum of the per-view ones (summed in the kernel),
gradcheck, the trainable rows, shape errors, opcheck; and the renderer's helpers built on it
(sh_colors_views, project_views). On CUDA the same equalities through both kernels (staged and
plain), and CUDA against the CPU."""
from __future__ import annotations

import pytest
import torch

from tiger.ops.sh import sh_to_color
from tiger.render.rasterize import project_for_raster, project_views, sh_colors, sh_colors_views

from ..render.devices import CUDA_SKIP, DEVICES
from ..render.scenes import camera, random_scene
from .opargs import F64, ops

DTYPES = [pytest.param(F64, id="f64"), pytest.param(torch.float32, id="f32")]


def _inputs(views: int, n: int = 300, degree: int = 3, dtype=F64, device="cpu", seed: int = 0):
    """V views' directions to N Gaussians (n = 300: several 64-row staged blocks and a ragged
    last one), a scene's DC band [N, 1, 3] and a strided slice of its higher bands (read in
    place), per-view visibility with rows culled in some views and one row culled in all, and
    per-view output gradients."""
    g = torch.Generator().manual_seed(seed + 100 * views + degree)
    dirs = torch.randn(views, n, 3, generator=g, dtype=F64) * 2
    dc = torch.randn(n, 1, 3, generator=g, dtype=F64)
    rest_all = torch.randn(n, 15, 3, generator=g, dtype=F64)
    visible = torch.rand(views, n, generator=g) > 0.3
    visible[:, 5] = False  # culled in every view
    v_colors = torch.randn(views, n, 3, generator=g, dtype=F64)
    k1 = (degree + 1) ** 2 - 1
    to = lambda t: t.to(device=device, dtype=dtype if t.is_floating_point() else t.dtype)  # noqa: E731
    return to(dirs), to(dc), to(rest_all), k1, to(visible), to(v_colors)


def _run(dirs, dc, rest_all, k1, degree, visible, v_colors, staged=True, trainable=None):
    """sh_to_color's output and the gradients of (dirs, dc, rest_all) for output gradient v_colors."""
    d, c, r = (t.detach().clone().requires_grad_() for t in (dirs, dc, rest_all))
    out = sh_to_color(d, c, degree, visible, r[:, :k1] if k1 else None, trainable=trainable, _staged=staged)
    out.backward(v_colors)
    return out.detach(), d.grad, c.grad, r.grad if r.grad is not None else torch.zeros_like(r)


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("views", [1, 2, 5])
@pytest.mark.parametrize("degree", [0, 1, 3])
@pytest.mark.parametrize("staged", [True, False])
def test_each_view_is_its_one_view_call(device, dtype, views, degree, staged):
    """View v of the V-view call: the one-view call's colours and dirs gradient bit for bit; the
    coefficient gradients equal the sum of the one-view calls' (bit for bit with one view)."""
    dirs, dc, rest_all, k1, vis, vc = _inputs(views, degree=degree, dtype=dtype, device=device)
    out, g_dirs, g_dc, g_rest = _run(dirs, dc, rest_all, k1, degree, vis, vc, staged)
    assert out.shape == (views, dirs.shape[1], 3)
    sum_dc, sum_rest = torch.zeros_like(dc), torch.zeros_like(rest_all)
    for v in range(views):
        one, one_dirs, one_dc, one_rest = _run(dirs[v], dc, rest_all, k1, degree, vis[v], vc[v], staged)
        assert torch.equal(out[v], one), v
        assert torch.equal(g_dirs[v], one_dirs), v
        sum_dc, sum_rest = sum_dc + one_dc, sum_rest + one_rest
    assert bool((out[~vis] == 0).all()) and bool((g_dirs[~vis] == 0).all())
    if views == 1:
        assert torch.equal(g_dc, sum_dc) and torch.equal(g_rest, sum_rest)
    tol = dict(rtol=1e-13, atol=1e-13) if dtype == F64 else dict(rtol=1e-5, atol=1e-5)
    torch.testing.assert_close(g_dc, sum_dc, **tol)
    torch.testing.assert_close(g_rest, sum_rest, **tol)
    assert int(g_dc[5].count_nonzero()) == 0 and int(g_rest[5].count_nonzero()) == 0  # culled in every view
    assert g_dc.abs().max() > 0 and (degree == 0 or g_rest[:, :k1].abs().max() > 0)
    assert int(g_rest[:, k1:].count_nonzero()) == 0  # bases past the degree: not read


def test_gradients_are_the_float64_sum_of_the_views():
    """The in-kernel sum against per-view gradients summed in float64 (tight): 4 views, degree 3,
    without a visibility mask (every view of every row adds)."""
    dirs, dc, rest_all, k1, _, vc = _inputs(4, n=97, degree=3)
    _, g_dirs, g_dc, g_rest = _run(dirs, dc, rest_all, k1, 3, None, vc)
    parts = [_run(dirs[v], dc, rest_all, k1, 3, None, vc[v]) for v in range(4)]
    torch.testing.assert_close(g_dc, sum(p[2] for p in parts), rtol=1e-14, atol=1e-14)
    torch.testing.assert_close(g_rest, sum(p[3] for p in parts), rtol=1e-14, atol=1e-14)
    assert torch.equal(g_dirs, torch.stack([p[1] for p in parts]))


@pytest.mark.parametrize("degree", [1, 3])
def test_gradcheck_views(degree):
    g = torch.Generator().manual_seed(degree)
    dirs = torch.randn(3, 4, 3, generator=g, dtype=F64).requires_grad_()
    dc = torch.randn(4, 1, 3, generator=g, dtype=F64).requires_grad_()
    rest = torch.randn(4, (degree + 1) ** 2 - 1, 3, generator=g, dtype=F64).requires_grad_()
    vis = torch.tensor([[True, False, True, True], [True, True, False, True], [False, True, True, True]])
    assert torch.autograd.gradcheck(lambda d, c, r: sh_to_color(d, c, degree, vis, r), (dirs, dc, rest))
    assert torch.autograd.gradcheck(lambda d, c, r: sh_to_color(d, c, degree, None, r), (dirs, dc, rest))


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("staged", [True, False])
def test_trainable_rows_over_views(device, dtype, staged):
    """trainable [N] (shared by the views): same colours; trainable rows get the unmasked call's
    gradients bit for bit, the others zero in every view (and no gradient work)."""
    dirs, dc, rest_all, k1, vis, vc = _inputs(4, degree=3, dtype=dtype, device=device, seed=7)
    n = dirs.shape[1]
    trainable = torch.zeros(n, dtype=torch.bool)
    trainable[2 * n // 3:] = True  # an edit's layout: frozen head, trainable tail
    trainable[[n // 17, n // 2, 5]] = True  # a few elsewhere (row 5: culled in every view)
    trainable = trainable.to(device)
    want = _run(dirs, dc, rest_all, k1, 3, vis, vc, staged)
    got = _run(dirs, dc, rest_all, k1, 3, vis, vc, staged, trainable)
    assert torch.equal(got[0], want[0])
    assert torch.equal(got[1][:, trainable], want[1][:, trainable])
    assert int(got[1][:, ~trainable].count_nonzero()) == 0
    for a, b in zip(got[2:], want[2:]):
        assert torch.equal(a[trainable], b[trainable])
        assert int(a[~trainable].count_nonzero()) == 0
        assert int(b[~trainable].count_nonzero()) > 0  # they did have gradients


def test_shape_errors_name_the_tensor_and_shape():
    dirs, dc, rest_all, _, vis, vc = _inputs(3, n=10, degree=1)
    rest = rest_all[:, :3]
    cases = [
        ((dirs[..., :2], dc, 1, vis, rest), r"dirs must have shape \[N, 3\] \(one view\) or \[V, N, 3\] \(V views\), got \[3, 10, 2\]"),
        ((dirs[None], dc, 1, None, rest), r"dirs must have shape \[N, 3\] .* got \[1, 3, 10, 3\]"),
        ((dirs, dc, 1, vis[0], rest), r"visible must have shape \[3, 10\] \(\[V, N\] like dirs \[3, 10, 3\]\), got \[10\]"),
        ((dirs[0], dc, 1, vis, rest), r"visible must have shape \[10\] \(\[N\] like dirs \[10, 3\]\), got \[3, 10\]"),
        ((dirs, dc, 1, vis.float(), rest), r"visible must have dtype Bool, got Float"),
        ((dirs, dc[:9], 1, vis, rest), r"coeffs must have shape \[10, \*, 3\], got \[9, 1, 3\]"),
        ((dirs, dc, 1, vis, rest[:9]), r"rest must have shape \[10, \*, 3\], got \[9, 3, 3\]"),
    ]
    for args, msg in cases:
        with pytest.raises(RuntimeError, match="tiger.sh_to_color: " + msg):
            sh_to_color(*args)
    with pytest.raises(RuntimeError, match=r"trainable must have shape \[10\], got \[3, 10\]"):
        sh_to_color(dirs, dc, 1, vis, rest, trainable=vis)
    with pytest.raises(RuntimeError, match=r"tiger.sh_to_color_backward: v_colors must have shape \[3, 10, 3\] "
                                           r"\(\[V, N, 3\] like dirs \[3, 10, 3\]\), got \[10, 3\]"):
        ops.sh_to_color_backward(dirs, dc, 1, vis, vc[0], rest)


def test_fake_kernels_check_the_view_shapes():
    """The fake kernels (torch.compile, opcheck) give the real shapes and refuse the bad ones with
    a message naming the tensor."""
    from torch._subclasses.fake_tensor import FakeTensorMode

    dirs, dc, rest_all, _, vis, vc = _inputs(3, n=10, degree=1)
    real = (dirs, dc, rest_all[:, :3].contiguous(), vis, vc)
    with FakeTensorMode() as mode:
        f = [mode.from_tensor(t) for t in real]
        assert ops.sh_to_color(f[0], f[1], 1, f[3], f[2]).shape == (3, 10, 3)
        v_dirs, v_dc, v_rest = ops.sh_to_color_backward(f[0], f[1], 1, f[3], f[4], f[2])
        assert (v_dirs.shape, v_dc.shape, v_rest.shape) == ((3, 10, 3), (10, 1, 3), (10, 3, 3))
        with pytest.raises(RuntimeError, match=r"visible must have shape \[3, 10\]"):
            ops.sh_to_color(f[0], f[1], 1, f[3][0], f[2])
        with pytest.raises(RuntimeError, match=r"v_colors must have shape \[3, 10, 3\]"):
            ops.sh_to_color_backward(f[0], f[1], 1, f[3], f[4][0], f[2])


@pytest.mark.parametrize("device", DEVICES)
def test_opcheck_views(device):
    dirs, dc, rest_all, _, vis, vc = _inputs(3, n=12, degree=2, device=device)
    rest = rest_all[:, :8].clone().requires_grad_()
    dirs, dc = dirs.requires_grad_(), dc.requires_grad_()
    trainable = (torch.arange(12) % 3 != 0).to(device)
    torch.library.opcheck(ops.sh_to_color.default, (dirs, dc, 2, vis, rest))
    torch.library.opcheck(ops.sh_to_color.default, (dirs, dc, 2, None, rest, True, trainable))
    torch.library.opcheck(ops.sh_to_color_backward.default,
                          (dirs.detach(), dc.detach(), 2, vis, vc, rest.detach(), True, trainable))


# -- the renderer's helpers -------------------------------------------------------------------


def _views_scene(views: int, dtype=F64, device="cpu", n: int = 40):
    m, q, s, o, _ = random_scene(n, 1, dtype=dtype, seed=3, scale_range=(0.1, 0.4), opacity_range=(0.3, 0.9))
    g = torch.Generator().manual_seed(4)
    dc = torch.randn(n, 1, 3, generator=g, dtype=F64).to(device, dtype)
    rest = torch.randn(n, 15, 3, generator=g, dtype=F64).to(device, dtype)
    vms, Ks = [], []
    for k in range(views):
        V, K = camera(31, 23, dtype=dtype)
        V = V.clone()
        V[0, 3] += 0.2 * k
        V[1, 3] -= 0.1 * k
        vms.append(V.to(device))
        Ks.append(K.to(device))
    return [t.to(device) for t in (m, q, s, o)], dc, rest, vms, Ks


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("dtype", DTYPES)
def test_sh_colors_views_and_project_views_are_the_one_view_helpers(device, dtype):
    """sh_colors_views' view v is sh_colors of camera v, and project_views' view v is
    project_for_raster of camera v, bit for bit (values and the per-view screen gradients);
    viewmats as a [V, 4, 4] tensor or a list."""
    (m, q, s, o), dc, rest, vms, Ks = _views_scene(3, dtype, device)
    vis = torch.rand(3, m.shape[0], generator=torch.Generator().manual_seed(5)).to(device) > 0.2
    batched = sh_colors_views(m, dc, torch.stack(vms), 3, vis, rest)
    assert batched.shape == (3, m.shape[0], 3)
    for v in range(3):
        assert torch.equal(batched[v], sh_colors(m, dc, vms[v], 3, vis[v], rest)), v
    ps = project_views(m, q, s, o, dc, vms, Ks, 31, 23, sh_degree=3, sh_rest=rest)
    for v, p in enumerate(ps):
        one = project_for_raster(m, q, s, o, dc, vms[v], Ks[v], 31, 23, sh_degree=3, sh_rest=rest)
        for a, b, name in zip(p, one, one._fields):
            assert (a is None and b is None) or torch.equal(a, b), (v, name)
    with pytest.raises(ValueError, match="needs V >= 1 viewmats and as many Ks, got 3 viewmats and 2 Ks"):
        project_views(m, q, s, o, dc, vms, Ks[:2], 31, 23, sh_degree=3, sh_rest=rest)


def test_project_views_per_view_channels():
    """Without sh_degree, colors [V, N, C] give each view its own channels (render_views' SH
    colour in front of shared features)."""
    (m, q, s, o), _, _, vms, Ks = _views_scene(2)
    cols = torch.rand(2, m.shape[0], 4, generator=torch.Generator().manual_seed(6), dtype=F64)
    ps = project_views(m, q, s, o, cols, torch.stack(vms), torch.stack(Ks), 31, 23)
    for v, p in enumerate(ps):
        assert torch.equal(p.features, cols[v])
        assert torch.equal(p.means2d, project_for_raster(m, q, s, o, cols[v], vms[v], Ks[v], 31, 23).means2d)
    with pytest.raises(ValueError, match=r"per-view colors must have shape \[V=2, N, C\], got \[3, 40, 4\]"):
        project_views(m, q, s, o, cols[[0, 1, 1]], vms, Ks, 31, 23)


# -- CUDA --------------------------------------------------------------------------------------


@pytest.mark.cuda
@CUDA_SKIP
@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("views", [1, 4])
def test_cuda_views_match_the_cpu_and_staged_matches_plain(dtype, views):
    """The V-view CUDA kernels against the CPU kernels (float rounding: the CUDA compiler fuses
    multiply-adds differently) and the staged kernels against the plain ones (bit for bit)."""
    cpu = _inputs(views, n=1000, degree=3, dtype=dtype, seed=11)
    gpu = [t.cuda() if torch.is_tensor(t) else t for t in cpu]
    dirs, dc, rest_all, k1, vis, vc = gpu
    staged = _run(dirs, dc, rest_all, k1, 3, vis, vc, True)
    plain = _run(dirs, dc, rest_all, k1, 3, vis, vc, False)
    for a, b in zip(staged, plain):
        assert torch.equal(a, b)
    want = _run(cpu[0], cpu[1], cpu[2], k1, 3, cpu[4], cpu[5])
    tol = dict(rtol=1e-12, atol=1e-12) if dtype == F64 else dict(rtol=2e-5, atol=2e-5)
    for a, b in zip(staged, want):
        torch.testing.assert_close(a.cpu(), b, **tol)
