"""tiger::scaled_adam_ against torch.optim.Adam (float64) plus the relevance scaling written out
term by term, its scatter into full tensors, its errors, its registration (opcheck), and on a GPU
the CUDA kernel against the CPU one."""
from __future__ import annotations

import pytest
import torch

from tiger.ops.scaled_adam import scaled_adam_

F64 = torch.float64
SHAPES = [(7, 3), (7, 4), (7,), (7, 5, 3)]
LRS = [0.1, 0.01, 0.5, 0.002]


def _problem(dtype=F64, seed=0, device="cpu"):
    g = torch.Generator().manual_seed(seed)
    params = [torch.randn(s, generator=g, dtype=dtype).to(device) for s in SHAPES]
    grads = [[torch.randn(s, generator=g, dtype=dtype).to(device) for s in SHAPES] for _ in range(5)]
    weight = torch.rand(SHAPES[0][0], generator=g, dtype=dtype).to(device)
    return params, grads, weight


def _reference(params, grads, weight, betas=(0.9, 0.99), eps=1e-8):
    """torch's Adam (one group per tensor), then p <- p_old + w (p_adam - p_old) per step."""
    ps = [p.clone().requires_grad_(True) for p in params]
    adam = torch.optim.Adam([{"params": [p], "lr": lr} for p, lr in zip(ps, LRS)], betas=betas, eps=eps)
    for step_grads in grads:
        olds = [p.detach().clone() for p in ps]
        for p, gr in zip(ps, step_grads):
            p.grad = gr.clone()
        adam.step()
        with torch.no_grad():
            for p, old in zip(ps, olds):
                w = weight.view(-1, *([1] * (p.dim() - 1))) if weight is not None else 1.0
                p.copy_(old + w * (p - old))
    return [p.detach() for p in ps], adam


def _run(params, grads, weight, betas=(0.9, 0.99), eps=1e-8, targets=(), index=None):
    ps = [p.clone() for p in params]
    m = [torch.zeros_like(p) for p in ps]
    v = [torch.zeros_like(p) for p in ps]
    steps = [torch.zeros((), dtype=torch.float32, device=p.device) for p in ps]
    for step_grads in grads:
        scaled_adam_(ps, step_grads, m, v, steps, LRS, betas, eps, weight=weight, targets=targets, index=index)
    return ps, m, v, steps


@pytest.mark.parametrize("weighted", [True, False])
def test_equals_torch_adam_with_the_update_scaled_per_row(weighted):
    params, grads, weight = _problem()
    w = weight if weighted else None
    ref, adam = _reference(params, grads, w)
    got, m, v, steps = _run(params, grads, w)
    for a, b in zip(got, ref):
        torch.testing.assert_close(a, b, rtol=1e-12, atol=1e-12)
    for k, p in enumerate(adam.param_groups):
        st = adam.state[p["params"][0]]
        torch.testing.assert_close(m[k], st["exp_avg"], rtol=1e-13, atol=1e-14)   # moments are Adam's, unscaled
        torch.testing.assert_close(v[k], st["exp_avg_sq"], rtol=1e-13, atol=1e-14)
        assert float(steps[k]) == float(st["step"]) == len(grads)


def test_rows_are_written_into_the_targets_and_nothing_else():
    params, grads, weight = _problem()
    index = torch.tensor([9, 0, 4, 2, 11, 6, 7])
    targets = [torch.full((12, *s[1:]), -5.0, dtype=F64) for s in SHAPES]
    got, *_ = _run(params, grads, weight, targets=targets, index=index)
    others = torch.ones(12, dtype=torch.bool)
    others[index] = False
    for t, p in zip(targets, got):
        assert torch.equal(t[index], p)
        assert torch.all(t[others] == -5.0)


def test_zero_weight_leaves_a_row_bit_identical():
    params, grads, weight = _problem()
    weight[3] = 0
    got, m, *_ = _run(params, grads, weight)
    for p, p0, mk in zip(got, params, m):
        assert torch.equal(p[3], p0[3]) and bool(mk[3].abs().sum() > 0)


def _args(n=2):
    params, grads, weight = _problem()
    ps, gs = params[:n], grads[0][:n]
    return [ps, gs, [torch.zeros_like(p) for p in ps], [torch.zeros_like(p) for p in ps],
            [torch.zeros(()) for _ in ps], LRS[:n], 0.9, 0.999, 1e-8, weight, [], None]


@pytest.mark.parametrize("change, match", [
    (lambda a: a.__setitem__(1, a[1][:1]), "one entry per param"),
    (lambda a: a[2].__setitem__(0, torch.zeros(3, 3, dtype=F64)), r"exp_avgs\[0\] must have params\[0\]'s shape"),
    (lambda a: a[1].__setitem__(1, a[1][1].float()), "dtype"),
    (lambda a: a[4].__setitem__(0, torch.zeros(2)), r"steps\[0\] must be one float32/float64 value"),
    (lambda a: a.__setitem__(9, torch.ones(3, dtype=F64)), "weight must have shape"),
    (lambda a: a.__setitem__(10, [torch.zeros(9, 3, dtype=F64)]), "give index or no targets"),
    (lambda a: a.__setitem__(6, 1.0), r"betas must lie in \[0, 1\)"),
    (lambda a: (a.__setitem__(11, torch.tensor([0, 1, 2, 3, 4, 5, 40])),
                a.__setitem__(10, [torch.zeros(9, 3, dtype=F64), torch.zeros(9, 4, dtype=F64)])),
     r"index\[6\] = 40 is not a row of targets\[0\]"),
])
def test_errors_name_the_argument(change, match):
    a = _args()
    change(a)
    with pytest.raises(RuntimeError, match=match):
        torch.ops.tiger.scaled_adam_(*a)


def test_opcheck():
    torch.library.opcheck(torch.ops.tiger.scaled_adam_.default, tuple(_args()),
                          test_utils=("test_schema", "test_faketensor"))


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
@pytest.mark.parametrize("dtype", [torch.float32, F64])
def test_cuda_equals_cpu(dtype):
    from tiger.ops import cuda_enabled

    if not cuda_enabled():
        pytest.skip("tiger built without CUDA")
    params, grads, weight = _problem(dtype)
    index = torch.tensor([9, 0, 4, 2, 11, 6, 7])
    tc = [torch.zeros((12, *s[1:]), dtype=dtype) for s in SHAPES]
    cpu = _run(params, grads, weight, targets=tc, index=index)
    dev = lambda xs: [x.cuda() for x in xs]  # noqa: E731
    tg = dev(tc)
    gpu = _run(dev(params), [dev(g) for g in grads], weight.cuda(), targets=[t.zero_() for t in tg],
               index=index.cuda())
    tol = dict(rtol=1e-5, atol=1e-6) if dtype == torch.float32 else dict(rtol=1e-12, atol=1e-13)
    for a_list, b_list in zip(cpu, gpu):
        for a, b in zip(a_list, b_list):
            torch.testing.assert_close(b.cpu(), a, **tol)
    for a, b in zip(tc, tg):
        torch.testing.assert_close(b.cpu(), a, **tol)


def test_no_rows_is_a_step_of_nothing():
    """A region with no trainable rows (a deletion refit with nothing to refit): counts still
    advance, as Adam's do for an empty parameter, and nothing else is touched."""
    p, g, m, v = (torch.zeros(0, 3, dtype=F64) for _ in range(4))
    step = torch.zeros(())
    target = torch.ones(5, 3, dtype=F64)
    scaled_adam_([p], [g], [m], [v], [step], [0.1], weight=torch.zeros(0, dtype=F64), targets=[target],
                 index=torch.zeros(0, dtype=torch.long))
    assert float(step) == 1.0 and torch.equal(target, torch.ones(5, 3, dtype=F64))
