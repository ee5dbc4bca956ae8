"""torch.ops.tiger.relevancy against a float64 PyTorch reference, LERF's formula, autograd, CUDA."""
from __future__ import annotations

import math

import pytest
import torch

import tiger  # noqa: F401  (registers the ops)

OP = torch.ops.tiger.relevancy
HAS_CUDA = torch.cuda.is_available() and tiger.ops.cuda_enabled()


def reference(f: torch.Tensor, q: torch.Tensor, n: torch.Tensor, t: float = 10.0, eps: float = 1e-12):
    """Plain float64 PyTorch: normalise, cosine, LERF pairwise softmax, min over the negatives."""
    f, q, n = f.double(), q.double(), n.double()
    fh = f / f.norm(dim=1, keepdim=True).clamp_min(eps)
    qh = q / q.norm(dim=1, keepdim=True).clamp_min(eps)
    nh = n / n.norm(dim=1, keepdim=True).clamp_min(eps)
    cos = fh @ qh.T
    if n.shape[0] == 0:
        return cos, None
    neg = fh @ nh.T  # [N, M]
    pair = torch.softmax(t * torch.stack(torch.broadcast_tensors(cos[:, :, None], neg[:, None, :]), -1), -1)
    return cos, pair[..., 0].min(dim=2).values


@pytest.mark.parametrize("dtype,tol", [(torch.float64, 1e-12), (torch.float32, 2e-6), (torch.float16, 2e-6)])
@pytest.mark.parametrize("n,d,q,m", [(1000, 64, 1, 4), (257, 64, 3, 4), (50, 512, 2, 4), (33, 3, 1, 1),
                                     (40, 63, 9, 2), (17, 64, 2, 0), (0, 64, 1, 4), (5, 64, 0, 4)])
def test_matches_reference(dtype, tol, n, d, q, m):
    g = torch.Generator().manual_seed(n * 7 + d + q + m)
    f = torch.randn(n, d, generator=g).to(dtype)
    pos, neg = torch.randn(q, d, generator=g), torch.randn(m, d, generator=g)
    cos, rel = OP(f, pos, neg)
    want_dtype = torch.float64 if dtype == torch.float64 else torch.float32
    assert cos.dtype == want_dtype and cos.shape == (n, q)
    # fp16 features are exact in the reference too (it upcasts the same fp16 values).
    ref_cos, ref_rel = reference(f, pos, neg)
    torch.testing.assert_close(cos.double(), ref_cos, atol=tol, rtol=0)
    if m == 0:
        assert rel.shape == (0,)
    else:
        assert rel.shape == (n, q) and rel.dtype == want_dtype
        torch.testing.assert_close(rel.double(), ref_rel, atol=10 * tol, rtol=0)


def test_lerf_formula_hand_computed():
    # f = (1, 0): cos with q = (3, 4)/5 is 0.6; negatives (0, 1) -> 0.8 and (1, 1)/sqrt2 -> 0.7071.
    f = torch.tensor([[2.0, 0.0]], dtype=torch.float64)
    q = torch.tensor([[3.0, 4.0]], dtype=torch.float64)
    n = torch.tensor([[0.0, 5.0], [1.0, 1.0], [-1.0, 0.0]], dtype=torch.float64)
    cos, rel = OP(f, q, n, 10.0)
    assert cos.item() == pytest.approx(0.6, abs=1e-15)
    # LERF: min over negatives of exp(10 c) / (exp(10 c) + exp(10 c_j)), by hand.
    c = 0.6
    per_neg = [math.exp(10 * c) / (math.exp(10 * c) + math.exp(10 * cj)) for cj in (0.0, 1 / math.sqrt(2), -1.0)]
    assert rel.item() == pytest.approx(min(per_neg), abs=1e-15)
    assert rel.item() == pytest.approx(1 / (1 + math.exp(-10 * (0.6 - 1 / math.sqrt(2)))), abs=1e-15)
    # A feature equal to the query and orthogonal to the only negative: e^10 / (e^10 + 1).
    _, r2 = OP(torch.tensor([[0.0, 1.0]]), torch.tensor([[0.0, 2.0]]), torch.tensor([[1.0, 0.0]]), 10.0)
    assert r2.item() == pytest.approx(math.exp(10) / (math.exp(10) + 1), rel=1e-6)
    # Temperature is honoured: t = 1 gives e^1 / (e^1 + e^0).
    _, r3 = OP(torch.tensor([[0.0, 1.0]]), torch.tensor([[0.0, 2.0]]), torch.tensor([[1.0, 0.0]]), 1.0)
    assert r3.item() == pytest.approx(math.e / (math.e + 1), rel=1e-6)


def test_extreme_values_no_overflow():
    # Huge temperature: exp(t c) overflows in the naive formula; the sigmoid form must not.
    f = torch.tensor([[1.0, 0.0], [0.0, 1.0]], dtype=torch.float32)
    cos, rel = OP(f, torch.tensor([[1.0, 0.0]]), torch.tensor([[0.0, 1.0]]), 1e4)
    assert torch.isfinite(rel).all()
    assert rel[0, 0].item() == 1.0 and rel[1, 0].item() == 0.0
    # Zero features (invisible Gaussians) give cosine 0, relevancy 0.5 against a zero-cosine negative.
    cos, rel = OP(torch.zeros(3, 8), torch.randn(1, 8), torch.randn(2, 8))
    assert (cos == 0).all() and torch.allclose(rel, torch.full_like(rel, 0.5))
    # fp16 near its range limit: the squared norm is accumulated in fp32.
    big = torch.full((4, 64), 60000.0, dtype=torch.float16)
    cos, _ = OP(big, torch.ones(1, 64), torch.zeros(0, 64))
    torch.testing.assert_close(cos, torch.ones(4, 1))


def test_errors_name_the_tensor():
    f = torch.randn(5, 8)
    with pytest.raises(RuntimeError, match="features must be \\[N, D\\]"):
        OP(torch.randn(5), torch.randn(1, 8), torch.randn(1, 8))
    with pytest.raises(RuntimeError, match="positives must be \\[Q, D\\]"):
        OP(f, torch.randn(1, 7), torch.randn(1, 8))
    with pytest.raises(RuntimeError, match="negatives must be \\[M, D\\]"):
        OP(f, torch.randn(1, 8), torch.randn(8))
    with pytest.raises(RuntimeError, match="features must be float16, float32 or float64"):
        OP(torch.ones(5, 8, dtype=torch.int32), torch.randn(1, 8), torch.randn(1, 8))
    with pytest.raises(RuntimeError, match="temperature"):
        OP(f, torch.randn(1, 8), torch.randn(1, 8), 0.0)


def test_gradcheck_float64():
    g = torch.Generator().manual_seed(3)
    f = torch.randn(6, 5, generator=g, dtype=torch.float64, requires_grad=True)
    q = torch.randn(2, 5, generator=g, dtype=torch.float64, requires_grad=True)
    n = torch.randn(3, 5, generator=g, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda a, b, c: OP(a, b, c, 3.0), (f, q, n))
    assert torch.autograd.gradcheck(lambda a, b: OP(a, b, torch.zeros(0, 5, dtype=torch.float64))[0], (f, q))


def test_backward_matches_autograd_of_reference():
    g = torch.Generator().manual_seed(4)
    f = torch.randn(20, 16, generator=g, dtype=torch.float64, requires_grad=True)
    q = torch.randn(3, 16, generator=g, dtype=torch.float64, requires_grad=True)
    n = torch.randn(4, 16, generator=g, dtype=torch.float64, requires_grad=True)
    w1, w2 = torch.randn(20, 3, generator=g, dtype=torch.float64), torch.randn(20, 3, generator=g, dtype=torch.float64)
    cos, rel = OP(f, q, n)
    got = torch.autograd.grad((cos * w1).sum() + (rel * w2).sum(), (f, q, n))
    rc, rr = reference(f, q, n)
    want = torch.autograd.grad((rc * w1).sum() + (rr * w2).sum(), (f, q, n))
    for a, b in zip(got, want):
        torch.testing.assert_close(a, b, atol=1e-10, rtol=1e-8)


def test_opcheck():
    f = torch.randn(9, 8, dtype=torch.float64, requires_grad=True)
    torch.library.opcheck(OP, (f, torch.randn(2, 8, dtype=torch.float64), torch.randn(3, 8, dtype=torch.float64), 10.0, 1e-12))
    torch.library.opcheck(OP, (torch.randn(9, 8), torch.randn(2, 8), torch.zeros(0, 8), 10.0, 1e-12))
    torch.library.opcheck(OP, (torch.randn(9, 8).half(), torch.randn(2, 8), torch.randn(1, 8), 10.0, 1e-12))


# ----------------------------------------------------------------------------------------- CUDA
cuda = pytest.mark.skipif(not HAS_CUDA, reason="needs a CUDA device and tiger built with CUDA")


@pytest.mark.cuda
@cuda
@pytest.mark.parametrize("dtype", [torch.float16, torch.float32, torch.float64])
@pytest.mark.parametrize("n,d,q,m", [(100_003, 64, 1, 4), (4099, 64, 1, 0), (5000, 64, 11, 4), (3001, 128, 2, 4),
                                     (777, 63, 3, 4), (513, 1024, 2, 4), (300, 64, 3, 9), (1, 8, 1, 1)])
def test_cuda_matches_cpu(dtype, n, d, q, m):
    g = torch.Generator().manual_seed(n + d)
    f = torch.randn(n, d, generator=g).to(dtype)
    pos, neg = torch.randn(q, d, generator=g), torch.randn(m, d, generator=g)
    c_cpu, r_cpu = OP(f, pos, neg)
    c_gpu, r_gpu = OP(f.cuda(), pos.cuda(), neg.cuda())
    tol = 1e-12 if dtype == torch.float64 else 3e-6
    torch.testing.assert_close(c_gpu.cpu(), c_cpu, atol=tol, rtol=0)
    torch.testing.assert_close(r_gpu.cpu(), r_cpu, atol=10 * tol, rtol=0)


@pytest.mark.cuda
@cuda
def test_cuda_misaligned_rows_use_generic_path():
    buf = torch.randn(1000 * 64 + 1, device="cuda").half()
    f = buf[1:].view(1000, 64)  # data pointer 2 bytes past a 16-byte boundary
    assert f.data_ptr() % 16 != 0
    pos, neg = torch.randn(2, 64, device="cuda"), torch.randn(4, 64, device="cuda")
    c, r = OP(f, pos, neg)
    rc, rr = reference(f.cpu(), pos.cpu(), neg.cpu())
    torch.testing.assert_close(c.double().cpu(), rc, atol=3e-6, rtol=0)
    torch.testing.assert_close(r.double().cpu(), rr, atol=3e-5, rtol=0)


@pytest.mark.cuda
@cuda
def test_cuda_opcheck_and_grad():
    f = torch.randn(50, 16, device="cuda", dtype=torch.float64, requires_grad=True)
    q = torch.randn(2, 16, device="cuda", dtype=torch.float64)
    n = torch.randn(3, 16, device="cuda", dtype=torch.float64)
    torch.library.opcheck(OP, (f, q, n, 10.0, 1e-12))
    assert torch.autograd.gradcheck(lambda a: OP(a, q, n, 2.0), (f[:6].detach().requires_grad_(),))


def test_public_function_is_the_op():
    from tiger.ops.relevancy import relevancy_scores

    g = torch.Generator().manual_seed(5)
    f, q, n = torch.randn(40, 16, generator=g), torch.randn(2, 16, generator=g), torch.randn(3, 16, generator=g)
    got = relevancy_scores(f, q, n, temperature=7.0)
    want = OP(f, q, n, 7.0, 1e-12)
    assert all(torch.equal(a, b) for a, b in zip(got, want))
