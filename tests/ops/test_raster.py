"""tiger::rasterize: gradcheck, opcheck, the features-only backward, the public function."""
from __future__ import annotations

import pytest
import torch
from torch.utils._python_dispatch import TorchDispatchMode

import tiger
from tiger.ops.raster import TILE_ORDERS, RasterKernelSettings, rasterize

from ..render.devices import DEVICES
from ..render.scenes import camera, random_scene
from .opargs import F64, _raster_args, ops


def _same(got, want, device: str) -> bool:
    """Bit-equal on the CPU; on CUDA the backward accumulates per-Gaussian gradients with
    atomics, whose order changes between calls, so float64 sums agree to rounding only."""
    if device == "cpu":
        return all(torch.equal(x, y) for x, y in zip(got, want))
    return all(torch.allclose(x, y, rtol=1e-12, atol=1e-13 * float(y.abs().max().clamp_min(1)))
               for x, y in zip(got, want))


@pytest.mark.parametrize("device", DEVICES)
class TestRasterize:
    def test_gradcheck(self, device):
        m2, cn, op, col, d, bg, to, ids, w, h = _raster_args(device=device)
        def f(m2, cn, op, col, d, bg):
            c, a, dep, _, _ = ops.rasterize(m2, cn, op, col, d, bg, to, ids, w, h, 16, 0.99, 1 / 255, 1e-4)
            return c, a, dep
        ins = [t.clone().requires_grad_() for t in (m2, cn, op, col, d, bg)]
        assert torch.autograd.gradcheck(f, ins, eps=1e-7, atol=1e-6, rtol=1e-5)

    def test_gradcheck_end_to_end_every_input(self, device):
        w, h = 18, 14
        m, q, s, o, col = random_scene(7, 3, seed=12, scale_range=(0.1, 0.3))
        V, K = camera(w, h)
        bg = torch.rand(3, dtype=F64)
        m, q, s, o, col, V, K, bg = [t.to(device) for t in (m, q, s, o, col, V, K, bg)]
        def f(*t):
            out = tiger.rasterize_gaussians(*t[:7], w, h, background=t[7])
            return out["color"], out["alpha"], out["depth"]
        ins = [t.clone().requires_grad_() for t in (m, q, s, o, col, V, K, bg)]
        assert torch.autograd.gradcheck(f, ins, eps=1e-7, atol=1e-6, rtol=1e-4)

    def test_opcheck(self, device):
        m2, cn, op, col, d, bg, to, ids, w, h = _raster_args(device=device)
        args = (m2, cn, op, col, d, bg, to, ids, w, h, 16, 0.99, 1 / 255, 1e-4)
        torch.library.opcheck(ops.rasterize.default, args)
        c, a, dep, cnt, tr = ops.rasterize(*args)
        vc, va, vd = torch.randn_like(c), torch.randn_like(a), torch.randn_like(dep)
        torch.library.opcheck(ops.rasterize_backward.default, (*args, tr, cnt, vc, va, vd))
        torch.library.opcheck(ops.rasterize_backward_colors.default,
                              (m2, cn, op, to, ids, w, h, 16, 0.99, 1 / 255, 1e-4, cnt, vc))


class _OpLog(TorchDispatchMode):
    def __init__(self):
        super().__init__()
        self.names: list[str] = []

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        self.names.append(str(func))
        return func(*args, **(kwargs or {}))


@pytest.mark.parametrize("device", DEVICES)
def test_features_only_backward_skips_geometry_and_matches_full(device):
    w, h = 40, 30
    m, q, s, o, col = random_scene(300, 64, seed=21)
    V, K = camera(w, h)
    m, q, s, o, col, V, K = [t.to(device) for t in (m, q, s, o, col, V, K)]
    wgt = torch.randn(h, w, 64, dtype=F64).to(device)
    c1 = col.clone().requires_grad_()
    out = tiger.rasterize_gaussians(m, q, s, o, c1, V, K, w, h)
    log = _OpLog()
    with log:
        (out["color"] * wgt).sum().backward()
    assert any("rasterize_backward_colors" in n for n in log.names)
    assert not any("rasterize_backward.default" in n or "project_gaussians_backward" in n
                   for n in log.names)
    # Same colour gradient as the full backward (geometry also requiring grad).
    c2 = col.clone().requires_grad_()
    m2 = m.clone().requires_grad_()
    out2 = tiger.rasterize_gaussians(m2, q, s, o, c2, V, K, w, h)
    (out2["color"] * wgt).sum().backward()
    assert float((c1.grad - c2.grad).abs().max()) <= 1e-10 * float(c2.grad.abs().max())


@pytest.mark.parametrize("device", DEVICES)
def test_public_function_is_the_op(device):
    args = _raster_args(device=device)
    got = rasterize(*args, tile_size=16, alpha_max=0.99, alpha_threshold=1 / 255, t_min=1e-4)
    want = ops.rasterize(*args, 16, 0.99, 1 / 255, 1e-4)
    assert all(torch.equal(a, b) for a, b in zip(got, want))


@pytest.mark.parametrize("device", DEVICES)
def test_backward_without_alpha_and_depth_gradients(device):
    """v_alpha / v_depth may be None (a colour-only loss): the same gradients as zeros, and the
    op's schema and fake kernel accept it."""
    m2, cn, op, col, d, bg, to, ids, w, h = _raster_args(device=device)
    args = (m2, cn, op, col, d, bg, to, ids, w, h, 16, 0.99, 1 / 255, 1e-4)
    c, a, dep, cnt, tr = ops.rasterize(*args)
    vc = torch.randn_like(c)
    got = ops.rasterize_backward(*args, tr, cnt, vc, None, None)
    want = ops.rasterize_backward(*args, tr, cnt, vc, torch.zeros_like(a), torch.zeros_like(dep))
    assert _same(got, want, device)
    va = torch.randn_like(a)
    got = ops.rasterize_backward(*args, tr, cnt, vc, va, None)
    want = ops.rasterize_backward(*args, tr, cnt, vc, va, torch.zeros_like(dep))
    assert _same(got, want, device)
    torch.library.opcheck(ops.rasterize_backward.default, (*args, tr, cnt, vc, None, None))


@pytest.mark.parametrize("device", DEVICES)
def test_eager_entry_matches_the_registered_autograd(device):
    """tiger.ops' functions run the kernels through an autograd.Function with the registered
    formula (no per-call schema walk): same outputs and gradients as torch.ops.tiger.* with
    inputs that require grad, for losses on each output (unused outputs get no zero tensors)."""
    w, h = 30, 22
    m, q, s, o, col = random_scene(60, 3, seed=31, scale_range=(0.05, 0.3))
    V, K = camera(w, h)
    m, q, s, o, col, V, K = [t.to(device) for t in (m, q, s, o, col, V, K)]
    wgt = torch.randn(h, w, 3, dtype=F64, generator=torch.Generator().manual_seed(2)).to(device)

    def run(eager: bool, loss_of: str):
        ins = [t.clone().requires_grad_() for t in (m, q, s, o, col)]
        if eager:
            p = tiger.ops.projection.project_gaussians(*ins[:4], V, K, w, h, 0.3, 0.01, 1e10, 1 / 255, False)
        else:
            p = ops.project_gaussians(*ins[:4], V, K, w, h, 0.3, 0.01, 1e10, 1 / 255, False)
        m2, cn, d, op, r = p
        to, ids = ops.bin_gaussians(m2.detach(), cn.detach(), op.detach(), d.detach(), r, w, h, 16, 1 / 255)
        args = (m2, cn, op, ins[4], d, None, to, ids, w, h, 16, 0.99, 1 / 255, 1e-4)
        out = rasterize(*args) if eager else ops.rasterize(*args)
        loss = {"color": (out[0] * wgt).sum(), "alpha": out[1].square().sum(),
                "depth": out[2].sum(), "all": (out[0] * wgt).sum() + out[1].sum() + out[2].sum()}[loss_of]
        loss.backward()
        return [t.detach() for t in out] + [t.grad for t in ins]

    for loss_of in ("color", "alpha", "depth", "all"):
        got, want = run(True, loss_of), run(False, loss_of)
        assert _same(got, want, device), loss_of
    with torch.no_grad():
        out = rasterize(*_raster_args(device=device), 16, 0.99, 1 / 255, 1e-4)
    assert not any(t.requires_grad for t in out)


class _ArgLog(TorchDispatchMode):
    """Every op call under it: (name, every argument in schema order, defaults filled in: the
    dispatcher leaves out trailing arguments equal to their defaults)."""

    def __init__(self):
        super().__init__()
        self.calls: list[tuple[str, tuple]] = []

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        kwargs = kwargs or {}
        full = list(args) + [kwargs.get(a.name, a.default_value)
                             for a in func._schema.arguments[len(args):]]
        self.calls.append((str(func), tuple(full)))
        return func(*args, **kwargs)


def _schema_defaults(op) -> dict:
    return {a.name: a.default_value for a in op.default._schema.arguments if a.has_default_value()}


def test_kernel_settings_defaults_are_the_op_schemas():
    """RasterKernelSettings repeats the defaults that csrc/raster/raster.h writes into the schemas."""
    s = RasterKernelSettings()
    assert _schema_defaults(ops.rasterize) == {
        "channel_block": s.forward_channel_block, "backward_channel_block": s.backward_channel_block,
        "colors_channel_block": s.colors_channel_block,
        "backward_pixels_per_thread": s.backward_pixels_per_thread, "views": 1, "trainable": None,
        "tile_order": s.tile_order_arg(), "warp_cull": s.warp_cull}
    assert _schema_defaults(ops.rasterize_backward) == {
        "channel_block": s.backward_channel_block, "pixels_per_thread": s.backward_pixels_per_thread,
        "views": 1, "trainable": None, "tile_order": s.tile_order_arg(), "warp_cull": s.warp_cull}
    assert _schema_defaults(ops.rasterize_backward_colors) == {"channel_block": s.colors_channel_block,
                                                               "views": 1, "trainable": None,
                                                               "tile_order": s.tile_order_arg(),
                                                               "warp_cull": s.warp_cull}
    assert (s.forward_channel_block, s.backward_pixels_per_thread, s.tile_order, s.warp_cull) == (
        64, 2, "heavy_first", True)
    assert TILE_ORDERS.index("heavy_first") == 1 and TILE_ORDERS.index("index") == 0  # raster.h's numbers


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("geometry", [True, False])
def test_kernel_settings_reach_the_backward_ops(device, geometry):
    """The forward op carries the backward's kernel choices; its autograd formula hands them to
    the full or the features-only backward op (read off the dispatched calls), and any choice
    gives the same values (the CPU kernels only check them)."""
    m2, cn, op, col, d, bg, to, ids, w, h = _raster_args(device=device)
    kernels = RasterKernelSettings(forward_channel_block=32, backward_channel_block=32,
                                   colors_channel_block=32, backward_pixels_per_thread=1, tile_order="index",
                                   warp_cull=False)
    grads = []
    for k in (RasterKernelSettings(), kernels):
        ins = [t.clone().requires_grad_(geometry) for t in (m2, cn, op)] + [col.clone().requires_grad_()]
        out = rasterize(*ins, d, bg, to, ids, w, h, 16, 0.99, 1 / 255, 1e-4, k)
        log = _ArgLog()
        with log:
            out[0].square().sum().backward()
        name = "tiger.rasterize_backward.default" if geometry else "tiger.rasterize_backward_colors.default"
        args = [a for n, a in log.calls if n == name]
        assert len(args) == 1, [n for n, _ in log.calls]
        want = ((k.backward_channel_block, k.backward_pixels_per_thread) if geometry
                else (k.colors_channel_block,))
        # then views (one image), trainable (all), tile_order, warp_cull
        assert args[0][-len(want) - 4:] == want + (1, None, k.tile_order_arg(), k.warp_cull)
        grads.append([out[0].detach()] + [t.grad for t in ins if t.grad is not None])
    assert _same(grads[1], grads[0], device)


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("field, value, message", [
    ("forward_channel_block", 16, "channel_block must be 64 or 32"),
    ("backward_channel_block", 128, "backward_channel_block must be 64 or 32"),
    ("colors_channel_block", 0, "colors_channel_block must be 64 or 32"),
    ("backward_pixels_per_thread", 4, "backward_pixels_per_thread must be 1 or 2"),
])
def test_kernel_settings_reject_bad_values(device, field, value, message):
    """Every device (and the fake kernel, for tracing) rejects a choice the CUDA kernels lack."""
    args = _raster_args(device=device)
    with pytest.raises(RuntimeError, match="tile_order must be 0"):  # the op's own argument
        ops.rasterize(*args, 16, 0.99, 1 / 255, 1e-4, *RasterKernelSettings().op_args(), 1, None, 2)
    bad = RasterKernelSettings(**{field: value})
    with pytest.raises(RuntimeError, match=message):
        rasterize(*args, 16, 0.99, 1 / 255, 1e-4, bad)
    from torch._subclasses.fake_tensor import FakeTensorMode
    with FakeTensorMode() as mode, pytest.raises(RuntimeError, match=message):
        fake = [mode.from_tensor(t) if isinstance(t, torch.Tensor) else t for t in args]
        ops.rasterize(*fake, 16, 0.99, 1 / 255, 1e-4, *bad.op_args())


@pytest.mark.parametrize("device", DEVICES)
def test_opcheck_with_other_kernel_settings(device):
    m2, cn, op, col, d, bg, to, ids, w, h = _raster_args(device=device)
    args = (m2, cn, op, col, d, bg, to, ids, w, h, 16, 0.99, 1 / 255, 1e-4)
    torch.library.opcheck(ops.rasterize.default, (*args, 32, 32, 32, 1))
    torch.library.opcheck(ops.rasterize.default, (*args, 64, 64, 64, 2, 1, None, 0))
    torch.library.opcheck(ops.rasterize.default, (*args, 64, 64, 64, 2, 1, None, 1, False))
    c, a, dep, cnt, tr = ops.rasterize(*args)
    vc, va, vd = torch.randn_like(c), torch.randn_like(a), torch.randn_like(dep)
    torch.library.opcheck(ops.rasterize_backward.default, (*args, tr, cnt, vc, va, vd, 32, 1))
    torch.library.opcheck(ops.rasterize_backward.default, (*args, tr, cnt, vc, va, vd, 64, 2, 1, None, 0))
    torch.library.opcheck(ops.rasterize_backward.default, (*args, tr, cnt, vc, va, vd, 64, 1, 1, None, 1, False))
    torch.library.opcheck(ops.rasterize_backward_colors.default,
                          (m2, cn, op, to, ids, w, h, 16, 0.99, 1 / 255, 1e-4, cnt, vc, 32))
    torch.library.opcheck(ops.rasterize_backward_colors.default,
                          (m2, cn, op, to, ids, w, h, 16, 0.99, 1 / 255, 1e-4, cnt, vc, 64, 1, None, 0))
    torch.library.opcheck(ops.rasterize_backward_colors.default,
                          (m2, cn, op, to, ids, w, h, 16, 0.99, 1 / 255, 1e-4, cnt, vc, 64, 1, None, 1, False))


def test_tile_order_setting_is_checked():
    with pytest.raises(ValueError, match="tile_order must be one of"):
        RasterKernelSettings(tile_order="random")


def test_rasterize_gaussians_passes_kernel_settings_down():
    """rasterize_gaussians' binning= / kernels= (RasterSettings' fields) reach the binning and the
    compositing ops as their arguments, op by op (a render recording gradients) and through
    render_forward (one without); the image is the same."""
    from tiger.ops.binning import BinningSettings

    w, h = 24, 20
    m, q, s, o, col = random_scene(30, 3, seed=5, scale_range=(0.05, 0.3))
    V, K = camera(w, h)
    binning = BinningSettings(path="global", block_sort_keys=64, warp_sort_keys=8, giant_tiles=9,
                              _serial=True)
    kernels = RasterKernelSettings(32, 32, 64, 1, "index", False)
    log = _ArgLog()
    with log:
        got = tiger.rasterize_gaussians(m, q, s, o, col.requires_grad_(), V, K, w, h, binning=binning,
                                        kernels=kernels)
    want = tiger.rasterize_gaussians(m, q, s, o, col, V, K, w, h)
    calls = dict(log.calls)
    assert calls["tiger.bin_gaussians.default"][-6:] == binning.op_args() + (1,)  # views last
    # then views, trainable, tile_order, warp_cull
    assert calls["tiger.rasterize.default"][-8:] == kernels.op_args() + (1, None, 0, False)
    assert torch.equal(got["color"], want["color"])
    log = _ArgLog()
    with log, torch.no_grad():
        got = tiger.rasterize_gaussians(m, q, s, o, col, V, K, w, h, binning=binning, kernels=kernels)
    assert dict(log.calls)["tiger.render_forward.default"][-8:] == binning.op_args() + (32, 0, False)
    assert torch.equal(got["color"], want["color"])


def test_one_pixel_warp_layout_is_the_measured_8x4_block():
    """The one-pixel-per-thread kernels give a warp an 8-wide, 4-tall pixel block of a 16-px tile
    (``warp_block`` in csrc/raster/raster_kernels.cuh, followed by ``tile_pixel`` and
    ``warp_span<1>``): of the layouts measured on the H100
    (benchmarks/gpu/results/raster_warp_layout_ab_h100.txt: 'head' = two rows of 16, '8x4', 'box'
    = 8x4 with a bounding-box pre-test), 8x4 drew the fox's raster forward fastest on both machines
    that ran it and the edit's one-pixel backward faster than rows. A change there must be
    re-measured. The block layout also has to tile the 16-px tile exactly (checked from the source's
    constants)."""
    import re
    from pathlib import Path

    root = Path(__file__).resolve().parents[2]
    src = (root / "csrc/raster/raster_kernels.cuh").read_text()
    assert "const int per_row = tile_size >> 3;" in src
    assert "return WarpBlock{8 * (warp % per_row), 4 * (warp / per_row)};" in src
    assert "cx = w.c0 + (t & 7);" in src and "cy = w.r0 + ((t & 31) >> 3);" in src  # tile_pixel
    assert "c1 = wb.c0 + 7;" in src and "r1 = 32 * w < ts * ts ? wb.r0 + 3 : wb.r0 - 1;" in src  # warp_span<1>
    pixels = set()
    for t in range(256):  # the same arithmetic for a 16-px tile: every pixel once, a warp an 8x4 block
        w = t >> 5
        c0, r0 = 8 * (w % 2), 4 * (w // 2)
        cx, cy = c0 + (t & 7), r0 + ((t & 31) >> 3)
        assert c0 <= cx <= c0 + 7 and r0 <= cy <= r0 + 3
        pixels.add((cx, cy))
    assert len(pixels) == 256

    raw = (root / "benchmarks/gpu/results/raster_warp_layout_ab_h100.txt").read_text()
    fox_forward: dict[tuple[str, str], float] = {}
    edit_backward: dict[tuple[str, str], float] = {}
    for machine in ("A", "B", "C"):
        part = raw[raw.index(f"######## machine {machine}"):]
        part = part[:part.index("########", 8)] if "########" in part[8:] else part
        for build, body in re.findall(r"^==== real_scenes, build (\S+)\n(.*?)(?=^====|\Z)", part, re.M | re.S):
            m = re.search(r"^ +fox +3 +ours +(\S+) +(\S+) +(\S+) +(\S+)", body, re.M)
            fox_forward[(machine, build)] = float(m.group(4))
        for build, body in re.findall(r"^==== render_views --edit kernel choices, build (\S+)\n(.*?)(?=^====|\Z)",
                                      part, re.M | re.S):
            m = re.search(r"^edit views +heavy_first +1 +True +one +(\S+) +(\S+)", body, re.M)
            edit_backward[(machine, build)] = float(m.group(2))
    for machine in ("B", "C"):
        others = [v for (mm, b), v in fox_forward.items() if mm == machine and b != "8x4"]
        assert others and fox_forward[(machine, "8x4")] < min(others)
    for machine in ("A", "B"):
        assert edit_backward[(machine, "8x4")] < edit_backward[(machine, "head")]
