"""tiger::bin_gaussians: tile lists against brute force, opcheck, the public function."""
from __future__ import annotations

import pytest
import torch

from tiger.ops.binning import BinningSettings, bin_gaussians

from ..render.devices import DEVICES
from .opargs import F64, _projection_args, _raster_args, ops


@pytest.mark.parametrize("device", DEVICES)
class TestBinning:
    @pytest.mark.parametrize("dtype", [F64, torch.float32])
    def test_lists_match_brute_force(self, device, dtype):
        m, q, s, o, V, K, w, h = _projection_args(200, 70, 50, seed=4, dtype=dtype, device=device)
        m2, cn, d, op, r = ops.project_gaussians(m, q, s, o, V, K, w, h, 0.3, 0.01, 1e10, 1 / 255, False)
        to, ids = ops.bin_gaussians(m2, cn, op, d, r, w, h, 16, 1 / 255)
        tiles_x = (w + 15) // 16
        m2, cn, d, op, r, to, ids = [t.cpu() for t in (m2, cn, d, op, r, to, ids)]
        m2, cn, d, op = m2.double(), cn.double(), d.double(), op.double()
        ys, xs = torch.meshgrid(torch.arange(h, dtype=F64), torch.arange(w, dtype=F64), indexing="ij")
        for t in range(to.numel() - 1):
            tx, ty = t % tiles_x, t // tiles_x
            lst = ids[to[t]:to[t + 1]].long()
            # front to back
            assert bool((d[lst][1:] >= d[lst][:-1]).all())
            # every Gaussian reaching alpha >= 1/255 at a pixel of this tile is listed
            px = xs[ty * 16:(ty + 1) * 16, tx * 16:(tx + 1) * 16].reshape(-1) + 0.5
            py = ys[ty * 16:(ty + 1) * 16, tx * 16:(tx + 1) * 16].reshape(-1) + 0.5
            dx = px[:, None] - m2[:, 0]
            dy = py[:, None] - m2[:, 1]
            qf = cn[:, 0] * dx * dx + 2 * cn[:, 1] * dx * dy + cn[:, 2] * dy * dy
            touches = ((op * torch.exp(-0.5 * qf)) >= 1 / 255).any(0) & (r[:, 0] > 0)
            need = set(torch.nonzero(touches).flatten().tolist())
            assert need <= set(lst.tolist())

    def test_opcheck(self, device):
        m2, cn, op, col, d, bg, to, ids, w, h = _raster_args(device=device)
        r = torch.ones(m2.shape[0], 2, dtype=torch.int32, device=device) * 4
        torch.library.opcheck(ops.bin_gaussians.default, (m2, cn, op, d, r, w, h, 16, 1 / 255),
                              test_utils=("test_schema", "test_faketensor"))
        other = BinningSettings(path="global", block_sort_keys=2, warp_sort_keys=1, giant_tiles=1,
                                _serial=True)
        torch.library.opcheck(ops.bin_gaussians.default,
                              (m2, cn, op, d, r, w, h, 16, 1 / 255, *other.op_args()),
                              test_utils=("test_schema", "test_faketensor"))


@pytest.mark.parametrize("device", DEVICES)
def test_public_function_is_the_op(device):
    m2, cn, op, col, d, bg, to, ids, w, h = _raster_args(device=device)
    r = torch.full((m2.shape[0], 2), 4, dtype=torch.int32, device=device)
    got = bin_gaussians(m2, cn, op, d, r, w, h, tile_size=8, alpha_threshold=1 / 255)
    want = ops.bin_gaussians(m2, cn, op, d, r, w, h, 8, 1 / 255)
    assert all(torch.equal(a, b) for a, b in zip(got, want))


def test_settings_defaults_are_the_op_schemas():
    """BinningSettings repeats the defaults that csrc/binning/binning_choices.h writes into the
    schema; "auto" switches paths at 2^18 Gaussians (tests/render/test_binning.py, on CUDA)."""
    schema = ops.bin_gaussians.default._schema
    defaults = {a.name: a.default_value for a in schema.arguments if a.has_default_value()}
    s = BinningSettings()
    assert defaults == {"path": s.path, "block_sort_keys": s.block_sort_keys,
                        "warp_sort_keys": s.warp_sort_keys, "giant_tiles": s.giant_tiles,
                        "_serial": s._serial, "views": 1}  # one image unless views= says more
    assert (s.path, s.block_sort_keys, s.warp_sort_keys, s.giant_tiles) == ("auto", 4096, 256, 512)


@pytest.mark.parametrize("device", DEVICES)
def test_every_setting_gives_the_same_lists(device):
    """The lists do not depend on the kernel choices (on the CPU, one walk: they are checked only;
    on CUDA, tests/render/test_binning.py runs every variant against the CPU)."""
    m2, cn, op, col, d, bg, to, ids, w, h = _raster_args(device=device)
    r = torch.full((m2.shape[0], 2), 6, dtype=torch.int32, device=device)
    want = bin_gaussians(m2, cn, op, d, r, w, h, 8, 1 / 255)
    for s in (BinningSettings(path="tiles", block_sort_keys=2, warp_sort_keys=1),
              BinningSettings(path="global", giant_tiles=1, _serial=True)):
        got = bin_gaussians(m2, cn, op, d, r, w, h, 8, 1 / 255, s)
        assert all(torch.equal(a, b) for a, b in zip(got, want)), s


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("field, value, message", [
    ("block_sort_keys", 0, r"block_sort_keys must be a power of two in \[2, 4096\], got 0"),
    ("block_sort_keys", 3, "block_sort_keys must be a power of two"),
    ("block_sort_keys", 8192, "block_sort_keys must be a power of two"),
    ("path", "fast", "path must be 'auto', 'tiles' or 'global', got 'fast'"),
    ("warp_sort_keys", 0, r"warp_sort_keys must be in \[1, 256\]"),
    ("warp_sort_keys", 257, r"warp_sort_keys must be in \[1, 256\], got 257"),
    ("giant_tiles", 0, "giant_tiles must be at least 1"),
])
def test_settings_reject_bad_values(device, field, value, message):
    """One line naming the argument, from the kernels of every device and from the fake kernel."""
    m2, cn, op, col, d, bg, to, ids, w, h = _raster_args(device=device)
    r = torch.full((m2.shape[0], 2), 4, dtype=torch.int32, device=device)
    bad = BinningSettings(**{field: value})
    with pytest.raises(RuntimeError, match=message):
        bin_gaussians(m2, cn, op, d, r, w, h, 16, 1 / 255, bad)
    from torch._subclasses.fake_tensor import FakeTensorMode
    with FakeTensorMode(allow_non_fake_inputs=False) as mode, pytest.raises(RuntimeError, match=message):
        fake = [mode.from_tensor(t) for t in (m2, cn, op, d, r)]
        ops.bin_gaussians(*fake, w, h, 16, 1 / 255, *bad.op_args())
