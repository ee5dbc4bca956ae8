"""CUDA kernels against the CPU kernels (same ops, same inputs), channel blocking, half-precision
channel storage, 64-bit intersection offsets, streams. Skipped without a GPU."""
from __future__ import annotations

import pytest
import torch

import tiger
from tiger.ops.raster import RasterKernelSettings

from .devices import CUDA
from .scenes import camera, random_scene
from .standard_scenes import standard_camera, standard_scene

pytestmark = CUDA
ops = torch.ops.tiger
F64, F32 = torch.float64, torch.float32


def rel(a: torch.Tensor, b: torch.Tensor) -> float:
    a, b = a.detach().double().cpu(), b.detach().double().cpu()
    return float((a - b).norm() / b.norm().clamp_min(1e-300))


def _pipeline_inputs(n, c, w, h, dtype, seed=0):
    m, q, s, o, col = random_scene(n, c, dtype=F64, seed=seed, scale_range=(0.03, 0.25))
    V, K = camera(w, h)
    bg = torch.rand(c, dtype=F64, generator=torch.Generator().manual_seed(seed))
    return [t.to(dtype) for t in (m, q, s, o, col, V, K, bg)]


def _project_and_bin(m, q, s, o, V, K, w, h):
    m2, cn, d, op, r = ops.project_gaussians(m, q, s, o, V, K, w, h, 0.3, 0.01, 1e10, 1 / 255, False)
    to, ids = ops.bin_gaussians(m2, cn, op, d, r, w, h, 16, 1 / 255)
    return m2, cn, d, op, r, to, ids


def _raster_all(device, m2, cn, op, col, d, bg, to, ids, w, h, seed=5,
                kernels: RasterKernelSettings = RasterKernelSettings()):
    """Forward, full backward and features-only backward of the raster op on `device`, with the
    CUDA kernel choices of `kernels`."""
    k = kernels
    args = [t.to(device) for t in (m2, cn, op, col, d, bg, to, ids)]
    order = k.launch_args()  # tile_order, warp_cull
    out = ops.rasterize(*args, w, h, 16, 0.99, 1 / 255, 1e-4, *k.op_args(), 1, None, *order)
    g = torch.Generator().manual_seed(seed)
    C = col.shape[1]
    vc = torch.randn(h, w, C, generator=g, dtype=F64).to(device, m2.dtype)
    va = torch.randn(h, w, generator=g, dtype=F64).to(device, m2.dtype)
    vd = torch.randn(h, w, generator=g, dtype=F64).to(device, m2.dtype)
    bwd = ops.rasterize_backward(*args, w, h, 16, 0.99, 1 / 255, 1e-4, out[4], out[3], vc, va, vd,
                                 k.backward_channel_block, k.backward_pixels_per_thread, 1, None, *order)
    feat = ops.rasterize_backward_colors(args[0], args[1], args[2], args[6], args[7], w, h, 16, 0.99,
                                         1 / 255, 1e-4, out[3], vc, k.colors_channel_block, 1, None, *order)
    return out, bwd, feat


@pytest.mark.parametrize("dtype", [F64, F32])
def test_projection_and_binning_match_cpu(dtype):
    w, h = 83, 61
    m, q, s, o, _, V, K, _ = _pipeline_inputs(700, 1, w, h, dtype, seed=1)
    cpu = _project_and_bin(m, q, s, o, V, K, w, h)
    gpu = _project_and_bin(*[t.cuda() for t in (m, q, s, o, V, K)], w, h)
    tol = 1e-12 if dtype == F64 else 2e-5
    for a, b in zip(cpu[:4], gpu[:4]):
        assert rel(b, a) <= tol
    same_radii = (cpu[4] == gpu[4].cpu()).all(1).double().mean()
    assert float(same_radii) >= (1.0 if dtype == F64 else 0.995)  # float32 ceil() may flip
    if dtype == F64:  # identical lists: same tiles, same (depth, id) order
        assert torch.equal(cpu[5], gpu[5].cpu()) and torch.equal(cpu[6], gpu[6].cpu())
    else:  # float32 tile tests may flip on a boundary pixel; the order is still front to back
        assert abs(int(gpu[6].numel()) - int(cpu[6].numel())) <= max(3, cpu[6].numel() // 1000)
    d, to, ids = gpu[2], gpu[5], gpu[6].long()
    for t in range(to.numel() - 1):
        seg = d[ids[to[t]:to[t + 1]]]
        assert bool((seg[1:] >= seg[:-1]).all())


@pytest.mark.parametrize("channels", [1, 3, 16, 33, 64, 67, 100, 130, 256])
@pytest.mark.parametrize("dtype", [F64, F32])
def test_raster_ops_match_cpu_any_channel_count(channels, dtype):
    """One launch for any C: single, main + tail and masked channel blocks all agree with CPU."""
    w, h = 45, 38  # partial edge tiles
    m, q, s, o, col, V, K, bg = _pipeline_inputs(250, channels, w, h, dtype, seed=channels)
    m2, cn, d, op, r, to, ids = _project_and_bin(m, q, s, o, V, K, w, h)
    cpu = _raster_all("cpu", m2, cn, op, col, d, bg, to, ids, w, h)
    gpu = _raster_all("cuda", m2, cn, op, col, d, bg, to, ids, w, h)
    # float32: a contribution right at the alpha threshold or a pixel right at t_min may
    # flip between the two compilers' exp(); the SPEC tolerances cover that.
    tol_f, tol_b = (1e-12, 1e-10) if dtype == F64 else (1e-5, 1e-4)
    for a, b in zip(cpu[0], gpu[0]):
        if a.dtype == torch.int32:
            same = float((a == b.cpu()).double().mean())
            assert same >= (1.0 if dtype == F64 else 0.99)
        else:
            assert rel(b, a) <= tol_f
    for name, a, b in zip(("means2d", "conics", "opac", "colors", "depths", "bg"), cpu[1], gpu[1]):
        assert rel(b, a) <= tol_b, name
    for a, b in zip(cpu[2], gpu[2]):
        assert rel(b, a) <= tol_b


@pytest.mark.parametrize("kernels", [RasterKernelSettings(forward_channel_block=32),
                                     RasterKernelSettings(backward_channel_block=32),
                                     RasterKernelSettings(colors_channel_block=32),
                                     RasterKernelSettings(backward_pixels_per_thread=1),
                                     RasterKernelSettings(tile_order="index"),
                                     RasterKernelSettings(warp_cull=False)], ids=str)
@pytest.mark.parametrize("channels", [3, 16, 67, 96])
def test_kernel_choices_same_result(kernels, channels):
    w, h = 40, 33
    m, q, s, o, col, V, K, bg = _pipeline_inputs(200, channels, w, h, F32, seed=7)
    m2, cn, d, op, r, to, ids = _project_and_bin(*[t.cuda() for t in (m, q, s, o, V, K)], w, h)
    base = _raster_all("cuda", m2, cn, op, col, d, bg, to, ids, w, h)
    alt = _raster_all("cuda", m2, cn, op, col, d, bg, to, ids, w, h, kernels=kernels)
    for group_a, group_b in zip(base, alt):
        for a, b in zip(group_a, group_b):
            assert rel(b, a) <= 1e-5


def test_tile_order_changes_no_value_on_uneven_lists():
    """Tiles drawn longest list first (the default) or in index order: the forward's outputs are
    the same bit for bit, the backward's up to the atomics' order, on a heavy-tailed scene whose
    tile lists run from tens to hundreds of entries, two views in one call."""
    from .standard_scenes import heavy_tailed_scene

    w, h = 320, 240
    s = heavy_tailed_scene(20_000, 3, device="cuda", seed=3)
    V, K = standard_camera(w, h, device="cuda")
    m2, cn, d, op, r = ops.project_gaussians(s["means"], s["quats"], s["scales"], s["opacities"], V, K, w, h,
                                             0.3, 0.01, 1e10, 1 / 255, False)
    # two views: the same projection twice, stacked (the second image's tiles after the first's)
    m2, cn, d, op, r = [torch.cat([t, t]) for t in (m2, cn, d, op, r)]
    to, ids = ops.bin_gaussians(m2, cn, op, d, r, w, h, 16, 1 / 255, views=2)
    lengths = (to[1:] - to[:-1]).cpu()
    assert lengths.max() >= 5 * lengths.median().clamp_min(1)  # uneven: the order changes the schedule
    col = torch.cat([s["colors"], s["colors"]]).float()
    bg = torch.rand(3, device="cuda")
    runs = []
    for order in ("index", "heavy_first"):
        k = RasterKernelSettings(tile_order=order)
        args = (m2, cn, op, col, d, bg, to, ids, w, h, 16, 0.99, 1 / 255, 1e-4)
        out = ops.rasterize(*args, *k.op_args(), 2, None, k.tile_order_arg())
        g = torch.Generator(device="cuda").manual_seed(4)
        vc = torch.randn(out[0].shape, device="cuda", generator=g)
        bwd = ops.rasterize_backward(*args, out[4], out[3], vc, None, None, 64, 2, 2, None, k.tile_order_arg())
        feat = ops.rasterize_backward_colors(m2, cn, op, to, ids, w, h, 16, 0.99, 1 / 255, 1e-4, out[3], vc,
                                             64, 2, None, k.tile_order_arg())
        runs.append((out, bwd, feat))
    assert all(torch.equal(a, b) for a, b in zip(runs[0][0], runs[1][0]))
    for a, b in zip(runs[0][1] + runs[0][2], runs[1][1] + runs[1][2]):
        assert rel(b, a) <= 1e-5


@pytest.mark.parametrize("tile_size", [16, 12, 8, 5])
@pytest.mark.parametrize("dtype", [F32, F64])
def test_warp_cull_changes_no_value(tile_size, dtype):
    """Each warp walking only the entries whose cutoff ellipse may reach its pixels (the default)
    or every entry: the forward's outputs are the same bit for bit, the backward ops' (one and
    two pixels a thread, all Gaussians or a trainable subset) up to the atomics' order. A
    heavy-tailed scene with a third of its Gaussians stretched 400:1 (the per-row test's rounding
    margin), two views in one call, tile sizes whose one-pixel warps hold an 8x4 block (16, 8),
    whole rows (12) or part of a row (5)."""
    from .standard_scenes import heavy_tailed_scene

    w, h = 300, 220
    s = heavy_tailed_scene(12_000, 3, device="cuda", seed=11)
    scales = s["scales"].clone()
    scales[::3, 0] *= 20.0
    scales[::3, 1] *= 0.05
    V, K = standard_camera(w, h, device="cuda")
    geom = [t.to(dtype) for t in (s["means"], s["quats"], scales, s["opacities"])]
    m2, cn, d, op, r = ops.project_gaussians(*geom, V.to(dtype), K.to(dtype), w, h, 0.3, 0.01, 1e10,
                                             1 / 255, False)
    m2, cn, d, op, r = [torch.cat([t, t]) for t in (m2, cn, d, op, r)]
    to, ids = ops.bin_gaussians(m2, cn, op, d, r, w, h, tile_size, 1 / 255, views=2)
    col = torch.cat([s["colors"], s["colors"]]).to(dtype)
    bg = torch.rand(3, device="cuda", dtype=dtype)
    trainable = torch.zeros(m2.shape[0], dtype=torch.bool, device="cuda")
    trainable[::7] = True
    args = (m2, cn, op, col, d, bg, to, ids, w, h, tile_size, 0.99, 1 / 255, 1e-4)
    runs = []
    for cull in (False, True):
        k = RasterKernelSettings(warp_cull=cull)
        out = ops.rasterize(*args, *k.op_args(), 2, None, *k.launch_args())
        g = torch.Generator(device="cuda").manual_seed(4)
        vc = torch.randn(out[0].shape, device="cuda", generator=g, dtype=dtype)
        va = torch.randn(out[1].shape, device="cuda", generator=g, dtype=dtype)
        grads = []
        for ppt in (1, 2):
            for train in (None, trainable):
                grads += ops.rasterize_backward(*args, out[4], out[3], vc, va, None, 64, ppt, 2, train,
                                                *k.launch_args())
        grads += ops.rasterize_backward_colors(m2, cn, op, to, ids, w, h, tile_size, 0.99, 1 / 255, 1e-4,
                                               out[3], vc, 64, 2, trainable, *k.launch_args())
        runs.append((out, grads))
    assert all(torch.equal(a, b) for a, b in zip(runs[0][0], runs[1][0]))
    for a, b in zip(runs[0][1], runs[1][1]):
        assert rel(b, a) <= (1e-5 if dtype == F32 else 1e-12)


@pytest.mark.parametrize("half", [torch.float16, torch.bfloat16])
def test_half_precision_channels(half):
    """float16/bfloat16 storage: same result as float32 channels holding the same values;
    accumulation stays float32 and gradients come back in the storage dtype."""
    w, h = 48, 40
    m, q, s, o, col, V, K, bg = [t.cuda() for t in _pipeline_inputs(400, 64, w, h, F32, seed=3)]
    col_h = col.to(half)
    col_f = col_h.float()
    g = torch.randn(h, w, 64, device="cuda")
    outs = []
    for c in (col_h, col_f):
        leaf = c.clone().requires_grad_()
        mm = m.clone().requires_grad_()
        out = tiger.rasterize_gaussians(mm, q, s, o, leaf, V, K, w, h, background=bg)
        (out["color"] * g).sum().backward()
        outs.append((out["color"], leaf.grad, mm.grad))
    assert outs[0][0].dtype == F32 and outs[0][1].dtype == half
    assert rel(outs[0][0], outs[1][0]) <= 1e-6
    assert rel(outs[0][2], outs[1][2]) <= 1e-5
    assert rel(outs[0][1].float(), outs[1][1]) <= (4e-3 if half == torch.float16 else 3e-2)
    # The CPU path upcasts and agrees.
    cpu = tiger.rasterize_gaussians(m.cpu(), q.cpu(), s.cpu(), o.cpu(), col_h.cpu(), V.cpu(), K.cpu(),
                                    w, h, background=bg.cpu())
    assert rel(outs[0][0], cpu["color"]) <= 2e-6


def test_tens_of_millions_of_intersections_64bit_offsets():
    """~30M tile-Gaussian pairs: offsets are int64, lists complete and front to back."""
    w, h = 1920, 1080
    s = standard_scene(4_000_000, 3, device="cuda")
    V, K = standard_camera(w, h, device="cuda")
    m2, cn, d, op, r, to, ids = _project_and_bin(s["means"], s["quats"], s["scales"], s["opacities"],
                                                 V, K, w, h)
    m = ids.numel()
    assert m > 20_000_000 and to.dtype == torch.int64 and int(to[-1]) == m and int(to[0]) == 0
    assert bool((to[1:] >= to[:-1]).all())
    assert int(ids.min()) >= 0 and int(ids.max()) < s["means"].shape[0]
    # Depth order inside every tile: the only descents are at tile boundaries.
    dd = d[ids.long()]
    desc = torch.nonzero(dd[1:] < dd[:-1]).flatten() + 1
    starts = torch.zeros(m + 1, dtype=torch.bool, device="cuda")
    starts[to] = True
    assert bool(starts[desc].all())
    # Every visible Gaussian's tile count agrees with the sum over its rows.
    counts = torch.bincount(ids.long(), minlength=s["means"].shape[0])
    assert int(counts.sum()) == m and bool((counts[r[:, 0] == 0] == 0).all())
    out = ops.rasterize(m2, cn, op, s["colors"], d, None, to, ids, w, h, 16, 0.99, 1 / 255, 1e-4)
    assert bool(torch.isfinite(out[0]).all()) and float(out[1].mean()) > 0.2


def test_runs_on_the_current_stream():
    w, h = 40, 30
    ins = [t.cuda() for t in _pipeline_inputs(300, 5, w, h, F32, seed=4)]
    ref = tiger.rasterize_gaussians(*ins[:7], w, h, background=ins[7])["color"]
    side = torch.cuda.Stream()
    side.wait_stream(torch.cuda.current_stream())
    with torch.cuda.stream(side):
        out = tiger.rasterize_gaussians(*ins[:7], w, h, background=ins[7])["color"]
    torch.cuda.current_stream().wait_stream(side)
    torch.cuda.synchronize()
    assert rel(out, ref) <= 1e-6


def test_backward_is_reproducible_up_to_atomic_order():
    w, h = 64, 48
    ins = [t.cuda() for t in _pipeline_inputs(800, 67, w, h, F32, seed=8)]
    grads = []
    for _ in range(2):
        leaves = [t.clone().requires_grad_() for t in ins[:5]]
        out = tiger.rasterize_gaussians(*leaves, ins[5], ins[6], w, h, background=ins[7])
        out["color"].square().sum().backward()
        grads.append([t.grad for t in leaves])
    for a, b in zip(*grads):
        assert rel(a, b) <= 1e-5


@pytest.mark.parametrize("tile_size", [8, 12])
def test_other_tile_sizes_match_cpu(tile_size):
    """Blocks of tile_size^2 pixels rounded up to whole warps (12 -> 160 threads)."""
    w, h = 45, 31
    ins = _pipeline_inputs(300, 19, w, h, F64, seed=9)
    outs = []
    for dev in ("cpu", "cuda"):
        leaves = [t.to(dev).clone().requires_grad_() for t in ins[:5]]
        out = tiger.rasterize_gaussians(*leaves, ins[5].to(dev), ins[6].to(dev), w, h,
                                        background=ins[7].to(dev), tile_size=tile_size)
        (out["color"].square().sum() + out["depth"].sum()).backward()
        outs.append((out["color"], out["alpha"], *[t.grad for t in leaves]))
    for a, b in zip(*outs):
        assert rel(b, a) <= 1e-10


def test_cuda_glue_errors_are_clear():
    w, h = 40, 40
    ins = [t.cuda() for t in _pipeline_inputs(20, 3, w, h, F32)]
    m2, cn, d, op, r, to, ids = _project_and_bin(*ins[:4], ins[5], ins[6], w, h)
    with pytest.raises(RuntimeError, match="colors must have the dtype of means2d"):
        ops.rasterize(m2, cn, op, ins[4].double(), d, None, to, ids, w, h, 16, 0.99, 1 / 255, 1e-4)
    with pytest.raises(RuntimeError, match="gaussian_ids is on cpu"):
        ops.rasterize(m2, cn, op, ins[4], d, None, to, ids.cpu(), w, h, 16, 0.99, 1 / 255, 1e-4)
    to32, ids32 = ops.bin_gaussians(m2, cn, op, d, r, w, h, 32, 1 / 255)
    with pytest.raises(RuntimeError, match="tile_size <= 16"):
        ops.rasterize(m2, cn, op, ins[4], d, None, to32, ids32, w, h, 32, 0.99, 1 / 255, 1e-4)
    with pytest.raises(ValueError, match=r"tile_size in \[1, 16\]"):
        tiger.rasterize_gaussians(*ins[:7], w, h, tile_size=32)


def test_projection_writes_every_row_without_zero_fills():
    """The CUDA projection (and its backward) allocate their outputs uninitialised and write
    every row: culled Gaussians get exact zeros even where the allocator hands out memory that
    held NaNs, and everything matches the CPU kernels."""
    w, h = 64, 48
    m, q, s, o, _, V, K, _ = _pipeline_inputs(500, 1, w, h, F64, seed=7)
    m = m.clone()
    m[::2, 2] = -50.0  # half of them behind the camera: culled
    g = torch.Generator().manual_seed(3)
    vs = [torch.randn(500, k, generator=g, dtype=F64).squeeze(1) for k in (2, 3, 1, 1)]
    cpu_f = ops.project_gaussians(m, q, s, o, V, K, w, h, 0.3, 0.01, 1e10, 1 / 255, False)
    cpu_b = ops.project_gaussians_backward(m, q, s, o, V, K, cpu_f[4], w, h, 0.3, False, *vs, True)
    for _ in range(2):
        poison = torch.full((1 << 22,), float("nan"), device="cuda", dtype=F64)
        del poison  # its block goes back to the caching allocator, NaNs and all
        args = [t.cuda() for t in (m, q, s, o, V, K)]
        gpu_f = ops.project_gaussians(*args, w, h, 0.3, 0.01, 1e10, 1 / 255, False)
        gpu_b = ops.project_gaussians_backward(*args, gpu_f[4], w, h, 0.3, False,
                                               *[v.cuda() for v in vs], True)
        culled = (gpu_f[4][:, 0] == 0).cpu()
        assert int(culled.sum()) >= 250
        for t in (*gpu_f, *gpu_b[:4]):
            assert int(t.cpu()[culled].count_nonzero()) == 0
        assert torch.equal(cpu_f[4], gpu_f[4].cpu())
        for a, b in zip((*cpu_f[:4], *cpu_b), (*gpu_f[:4], *gpu_b)):
            assert rel(b, a) <= 1e-10


def test_host_synchronisations_of_a_render(capfd):
    """One device synchronisation per forward (the binning's list size); the input checks
    (check_finite=True) add one, whatever the number of tensors checked."""
    import warnings
    w, h = 48, 40
    m, q, s, o, col, V, K, bg = [t.cuda() for t in _pipeline_inputs(300, 3, w, h, F32, seed=4)]

    def syncs(check_finite: bool) -> int:
        # A sync inside a custom op's C++ reaches Python's warnings only when the op was entered
        # through a Python binding; from the dispatcher, c10 prints it to stderr: count both.
        torch.cuda.synchronize()
        capfd.readouterr()
        torch.cuda.set_sync_debug_mode("warn")
        try:
            with warnings.catch_warnings(record=True) as caught:
                warnings.simplefilter("always")
                tiger.rasterize_gaussians(m, q, s, o, col, V, K, w, h, background=bg,
                                          check_finite=check_finite)
        finally:
            torch.cuda.set_sync_debug_mode(0)
        printed = capfd.readouterr().err.count("called a synchronizing CUDA operation")
        return sum("synchroniz" in str(c.message) for c in caught) + printed

    assert syncs(False) == 1
    assert syncs(True) == 2


@pytest.mark.parametrize("channels, ppt_default", [(3, 2), (16, 2), (17, 1), (64, 1)])
def test_backward_pixels_per_thread_default(channels, ppt_default):
    """Two pixels per backward thread for float32 channel blocks <= 16, one beyond, and
    backward_pixels_per_thread=1 forces one: the default, measured on the H100 (float32 C = 3
    backward of 1M Gaussians at 1080x1920: 3.09 -> 2.28 ms per training step; docs/BENCHMARKS.md).
    Read off the launched kernel's template arguments."""
    from torch.profiler import ProfilerActivity, profile

    w, h = 40, 33
    m, q, s, o, col, V, K, bg = _pipeline_inputs(200, channels, w, h, F32, seed=11)
    m2, cn, d, op, r, to, ids = _project_and_bin(*[t.cuda() for t in (m, q, s, o, V, K)], w, h)

    def launched_ppt(kernels: RasterKernelSettings = RasterKernelSettings()) -> set:
        with profile(activities=[ProfilerActivity.CUDA]) as prof:
            _raster_all("cuda", m2, cn, op, col, d, bg, to, ids, w, h, kernels=kernels)
            torch.cuda.synchronize()
        names = [e.name for e in prof.events() if "raster_cuda::backward_kernel<" in e.name]
        assert names, "no backward kernel seen"
        return {int(n.split(">")[0].split(",")[-1]) for n in names}

    assert launched_ppt() == {ppt_default}
    assert launched_ppt(RasterKernelSettings(backward_pixels_per_thread=1)) == {1}


@pytest.mark.parametrize("channels, block", [(3, 4), (64, 64), (100, 64)])
def test_channel_block_choice_reaches_the_kernels(channels, block):
    """forward/backward/colors_channel_block = 32 launch kernels of 32-channel main blocks (C > 32)
    or tails of at most 32 channels; the default launches 64-channel blocks (read off the launched
    kernels' template arguments: <T, TC, CBM, CBT, ...>)."""
    from torch.profiler import ProfilerActivity, profile

    w, h = 40, 33
    m, q, s, o, col, V, K, bg = _pipeline_inputs(150, channels, w, h, F32, seed=12)
    m2, cn, d, op, r, to, ids = _project_and_bin(*[t.cuda() for t in (m, q, s, o, V, K)], w, h)

    def largest_block(kernels: RasterKernelSettings) -> dict:
        with profile(activities=[ProfilerActivity.CUDA]) as prof:
            _raster_all("cuda", m2, cn, op, col, d, bg, to, ids, w, h, kernels=kernels)
            torch.cuda.synchronize()
        out = {}
        for kind in ("forward_kernel<", "backward_kernel<", "backward_colors_kernel<"):
            names = [e.name for e in prof.events() if f"raster_cuda::{kind}" in e.name]
            assert names, f"no {kind} seen"
            args = names[0].split(kind)[1].split(">")[0].split(",")
            cbm_cbt = [int(a) for a in args[-3:-1]] if kind == "backward_kernel<" else [
                int(a) for a in args[-2:]]
            out[kind] = max(cbm_cbt)
        return out

    assert set(largest_block(RasterKernelSettings()).values()) == {block}
    narrow = RasterKernelSettings(forward_channel_block=32, backward_channel_block=32,
                                  colors_channel_block=32)
    assert set(largest_block(narrow).values()) == {min(block, 32)}
