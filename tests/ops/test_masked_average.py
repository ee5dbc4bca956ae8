"""tiger::masked_average against a plain PyTorch float64 reference (values and gradients)."""
import pytest
import torch

import tiger  # noqa: F401
from tiger.ops.masked_average import masked_average

CUDA = torch.cuda.is_available() and tiger.ops.cuda_enabled()


def reference(features, ids, m):
    c = features.shape[1]
    means = torch.zeros(m, c, dtype=features.dtype)
    counts = torch.zeros(m, dtype=torch.int64)
    for k in range(m):
        sel = ids == k
        counts[k] = sel.sum()
        if counts[k] > 0:
            means[k] = features[sel].mean(0)
    out = torch.where((ids >= 0)[:, None], means[ids.clamp_min(0)], features)
    return out, means, counts


def make(p=97, c=5, m=6, seed=0, dtype=torch.float64):
    g = torch.Generator().manual_seed(seed)
    f = torch.randn(p, c, generator=g, dtype=dtype)
    ids = torch.randint(-1, m, (p,), generator=g)
    ids[ids == m - 1] = -1  # leave the last mask empty
    return f, ids, m


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_values_match_reference(dtype):
    f, ids, m = make(dtype=dtype)
    out, means, counts = masked_average(f, ids, m)
    r_out, r_means, r_counts = reference(f.double(), ids, m)
    tol = 1e-12 if dtype == torch.float64 else 1e-5
    torch.testing.assert_close(out.double(), r_out, atol=tol, rtol=tol)
    torch.testing.assert_close(means.double(), r_means, atol=tol, rtol=tol)
    assert torch.equal(counts, r_counts)
    assert means[m - 1].abs().sum() == 0


def test_gradients_match_reference():
    f, ids, m = make(p=40, c=3, m=5)
    f1 = f.clone().requires_grad_()
    f2 = f.clone().requires_grad_()
    g_out = torch.randn(40, 3, dtype=torch.float64)
    g_means = torch.randn(5, 3, dtype=torch.float64)
    out, means, _ = masked_average(f1, ids, m)
    ((out * g_out).sum() + (means * g_means).sum()).backward()
    r_out, r_means, _ = reference(f2, ids, m)
    ((r_out * g_out).sum() + (r_means * g_means).sum()).backward()
    torch.testing.assert_close(f1.grad, f2.grad, atol=1e-12, rtol=1e-12)


def test_gradcheck_and_opcheck():
    f, ids, m = make(p=30, c=3, m=4)
    f.requires_grad_()
    assert torch.autograd.gradcheck(lambda x: masked_average(x, ids, m)[:2], (f,))
    torch.library.opcheck(torch.ops.tiger.masked_average, (f, ids, m))
    torch.library.opcheck(torch.ops.tiger.masked_average, (f.detach(), ids, 0 if ids.max() < 0 else m))


def test_no_masks_and_empty():
    f = torch.randn(10, 4, dtype=torch.float64)
    ids = torch.full((10,), -1)
    out, means, counts = masked_average(f, ids, 0)
    assert torch.equal(out, f) and means.shape == (0, 4) and counts.shape == (0,)
    out, means, counts = masked_average(torch.zeros(0, 4), torch.zeros(0, dtype=torch.int64), 3)
    assert out.shape == (0, 4) and torch.equal(counts, torch.zeros(3, dtype=torch.int64))


def test_bad_inputs_name_the_problem():
    f = torch.randn(10, 4)
    with pytest.raises(RuntimeError, match="ids must lie in"):
        masked_average(f, torch.full((10,), 7), 3)
    with pytest.raises(RuntimeError, match="ids must be \\[P\\]"):
        torch.ops.tiger.masked_average(f, torch.zeros(9, dtype=torch.int64), 1)
    with pytest.raises(RuntimeError, match="features must be \\[P, C\\]"):
        torch.ops.tiger.masked_average(torch.randn(10), torch.zeros(10, dtype=torch.int64), 1)
    with pytest.raises(RuntimeError, match="float32 or float64"):
        torch.ops.tiger.masked_average(f.half(), torch.zeros(10, dtype=torch.int64), 1)


@pytest.mark.cuda
@pytest.mark.skipif(not CUDA, reason="needs CUDA and tiger's CUDA kernels")
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_cuda_matches_cpu(dtype):
    f, ids, m = make(p=5000, c=70, m=40, dtype=dtype)
    ids = torch.sort(ids).values  # long runs, the case the run-length accumulation targets
    f1 = f.clone().requires_grad_()
    f2 = f.cuda().requires_grad_()
    o1, m1, c1 = masked_average(f1, ids, m)
    o2, m2, c2 = masked_average(f2, ids.cuda(), m)
    tol = 1e-10 if dtype == torch.float64 else 1e-4
    torch.testing.assert_close(o2.cpu(), o1, atol=tol, rtol=tol)
    torch.testing.assert_close(m2.cpu(), m1, atol=tol, rtol=tol)
    assert torch.equal(c2.cpu(), c1)
    g = torch.randn_like(f)
    (o1 * g).sum().backward()
    (o2 * g.cuda()).sum().backward()
    torch.testing.assert_close(f2.grad.cpu(), f1.grad, atol=tol, rtol=tol)
    torch.library.opcheck(torch.ops.tiger.masked_average, (f2.detach(), ids.cuda(), m))
