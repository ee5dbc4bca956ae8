"""tiger::project_gaussians' trainable rows: the same values; the trainable rows' gradients equal the
full backward's, zero for the others, and the camera's gradient holds the trainable rows' terms only."""
from __future__ import annotations

import pytest
import torch

from tiger.ops.projection import project_gaussians

from ..render.devices import DEVICES
from .opargs import _projection_args


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_trainable_rows_get_the_full_gradients_the_others_zero(device, dtype):
    m, q, s, o, V, K, w, h = _projection_args(300, 70, 50, seed=6, dtype=dtype, device=device)
    n = m.shape[0]
    trainable = torch.zeros(n, dtype=torch.bool, device=device)
    trainable[2 * n // 3:] = True
    trainable[n // 7] = True
    g = torch.Generator().manual_seed(2)
    ups = [torch.randn(*shape, generator=g, dtype=dtype).to(device) for shape in ((n, 2), (n, 3), (n,), (n,))]

    def run(tr, upstream):
        leaves = [t.detach().clone().requires_grad_() for t in (m, q, s, o, V, K)]
        out = project_gaussians(*leaves, w, h, 0.3, 0.01, 1e10, 1 / 255, False, tr)
        sum((a * b).sum() for a, b in zip(out[:4], upstream)).backward()
        return [t.detach() for t in out], [t.grad for t in leaves]

    want, want_g = run(None, ups)
    got, got_g = run(trainable, ups)
    assert all(torch.equal(a, b) for a, b in zip(got, want))
    for a, b in zip(got_g[:4], want_g[:4]):
        assert torch.equal(a[trainable], b[trainable])
        assert int(a[~trainable].count_nonzero()) == 0
    # the camera's gradient: the full backward's with the frozen rows' upstream gradients zeroed
    masked = [u * trainable.reshape(-1, *[1] * (u.dim() - 1)) for u in ups]
    _, ref_g = run(None, masked)
    for a, b in zip(got_g[4:], ref_g[4:]):
        torch.testing.assert_close(a, b, rtol=1e-12 if dtype == torch.float64 else 1e-5, atol=0)


@pytest.mark.parametrize("device", DEVICES)
def test_trainable_checks_and_opcheck(device):
    m, q, s, o, V, K, w, h = _projection_args(20, 30, 20, seed=1, dtype=torch.float32, device=device)
    tr = torch.ones(20, dtype=torch.bool, device=device)
    with pytest.raises(RuntimeError, match=r"trainable must have shape \[20\]"):
        project_gaussians(m, q, s, o, V, K, w, h, 0.3, 0.01, 1e10, 1 / 255, False, tr[:3])
    with pytest.raises(RuntimeError, match="trainable must have dtype Bool, got Int"):
        project_gaussians(m, q, s, o, V, K, w, h, 0.3, 0.01, 1e10, 1 / 255, False, tr.int())
    torch.library.opcheck(torch.ops.tiger.project_gaussians.default,
                          (m, q, s, o, V, K, w, h, 0.3, 0.01, 1e10, 1 / 255, False, tr),
                          test_utils=("test_schema", "test_faketensor", "test_autograd_registration"))
