"""tiger::bin_gaussians: tile lists against brute force, opcheck, the public function."""
from __future__ import annotations

import pytest
import torch

from tiger.ops.binning import bin_gaussians

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


@pytest.mark.parametrize("device", DEVICES)
def test_public_function_is_the_op(device):
    m2, cn, op, col, d, bg, to, ids, w, h = _raster_args(device=device)
    r = torch.full((m2.shape[0], 2), 4, dtype=torch.int32, device=device)
    got = bin_gaussians(m2, cn, op, d, r, w, h, tile_size=8, alpha_threshold=1 / 255)
    want = ops.bin_gaussians(m2, cn, op, d, r, w, h, 8, 1 / 255)
    assert all(torch.equal(a, b) for a, b in zip(got, want))
