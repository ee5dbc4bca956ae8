"""tiger::sh_to_color's trainable rows: the same values, the trainable rows' gradients equal to the
full backward's, zero (and no gradient work) for the others; on CUDA through both kernels."""
from __future__ import annotations

import pytest
import torch

from tiger.ops.sh import sh_to_color

from ..render.devices import DEVICES


def _inputs(device, dtype, n=300, degree=3, seed=0):
    g = torch.Generator().manual_seed(seed)
    dirs = torch.randn(n, 3, generator=g, dtype=torch.float64)
    dc = torch.randn(n, 1, 3, generator=g, dtype=torch.float64)
    rest = torch.randn(n, (degree + 1) ** 2 - 1, 3, generator=g, dtype=torch.float64)
    visible = torch.rand(n, generator=g) > 0.2
    trainable = torch.zeros(n, dtype=torch.bool)
    trainable[2 * n // 3:] = True  # an edit's layout: frozen head, trainable tail
    trainable[n // 17] = trainable[n // 2] = True  # and a few elsewhere (whole 64-row blocks frozen or not)
    return [t.to(device) for t in (dirs.to(dtype), dc.to(dtype), rest.to(dtype), visible, trainable)]


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
@pytest.mark.parametrize("staged", [True, False])
def test_trainable_rows_get_the_full_gradients_the_others_zero(device, dtype, staged):
    dirs, dc, rest, visible, trainable = _inputs(device, dtype)
    v = torch.randn(dirs.shape[0], 3, dtype=dtype, generator=torch.Generator().manual_seed(3)).to(device)

    def run(tr):
        leaves = [t.detach().clone().requires_grad_() for t in (dirs, dc, rest)]
        out = sh_to_color(leaves[0], leaves[1], 3, visible, leaves[2], trainable=tr, _staged=staged)
        out.backward(v)
        return out.detach(), [t.grad for t in leaves]

    want, want_g = run(None)
    got, got_g = run(trainable)
    assert torch.equal(got, want)
    for a, b in zip(got_g, want_g):
        assert torch.equal(a[trainable], b[trainable])
        assert int(a[~trainable].count_nonzero()) == 0
        assert int(b[~trainable & visible].count_nonzero()) > 0  # they did have gradients


@pytest.mark.parametrize("device", DEVICES)
def test_trainable_checks(device):
    dirs, dc, rest, visible, trainable = _inputs(device, torch.float32, n=20)
    with pytest.raises(RuntimeError, match=r"trainable must have shape \[20\]"):
        sh_to_color(dirs, dc, 3, visible, rest, trainable=trainable[:5])
    with pytest.raises(RuntimeError, match="trainable must have dtype Bool, got Float"):
        sh_to_color(dirs, dc, 3, visible, rest, trainable=trainable.float())
    torch.library.opcheck(torch.ops.tiger.sh_to_color.default, (dirs, dc, 3, visible, rest, True, trainable),
                          test_utils=("test_schema", "test_faketensor", "test_autograd_registration"))
