"""A small CUDA workload of tiger::group_norm and tiger::channel_bias_add (the other kernel of the
fused diffusion models) for compute-sanitizer (memcheck / racecheck):
forward and backward (with and without parameter gradients, and the input gradient with a residual
gradient added) for every dtype, both layouts,
with and without SiLU, strided input biases, the one-launch input gradient, on shapes that take the 16-byte vector path, the scalar path (C or H·W
no multiple of the vector, an unaligned view), several row chunks and a several-pass column walk.
"""
from __future__ import annotations

import torch

import tiger
from tiger.ops.channel_bias import channel_bias_add
from tiger.ops.group_norm import group_norm, group_norm_input_grad, group_norm_with_stats

SHAPES = [(2, 128, 9, 7, 32), (2, 30, 5, 7, 3), (1, 1280, 4, 4, 32), (1, 64, 40, 24, 8)]


def run(shape, dtype, channels_last, silu, param_grads):
    n, c, h, w, g = shape
    x = torch.randn(n, c, h, w, device="cuda", dtype=dtype)
    if channels_last:
        x = x.contiguous(memory_format=torch.channels_last)
    x.requires_grad_()
    wt = torch.randn(c, device="cuda", dtype=dtype, requires_grad=param_grads)
    b = torch.randn(c, device="cuda", dtype=torch.float32, requires_grad=param_grads) if dtype == torch.float32 else \
        torch.randn(c, device="cuda", dtype=dtype, requires_grad=param_grads)
    y = group_norm(x, g, wt, b, 1e-6, silu)
    y.backward(torch.randn_like(y))
    with torch.no_grad():  # the input gradient with a residual gradient added (a ResNet block's own backward)
        _, mean, rstd = group_norm_with_stats(x, g, wt, b, 1e-6, silu)
        dx = group_norm_input_grad(torch.randn_like(y), x, g, mean, rstd, wt, b, silu, residual_grad=torch.randn_like(y))
    torch.cuda.synchronize()
    assert bool(torch.isfinite(x.grad.float()).all()) and bool(torch.isfinite(dx.float()).all())
    print(f"ok {shape} {dtype} cl={channels_last} silu={silu} params={param_grads}", flush=True)


def main() -> None:
    assert tiger.ops.cuda_enabled() and torch.cuda.is_available()
    for shape in SHAPES:
        for dtype in (torch.float32, torch.bfloat16, torch.float16):
            for cl in (False, True):
                run(shape, dtype, cl, silu=True, param_grads=dtype == torch.float32)
    run(SHAPES[0], torch.bfloat16, True, silu=False, param_grads=True)
    base = torch.randn(1 + 2 * 8 * 8 * 16, device="cuda", dtype=torch.bfloat16)
    xv = base[1:].view(2, 8, 8, 16).permute(0, 3, 1, 2).requires_grad_()  # unaligned channels-last view
    group_norm(xv, 4, None, None, 1e-6, True).sum().backward()
    torch.cuda.synchronize()
    print("ok unaligned view", flush=True)
    for n, c, h, w, g in SHAPES:  # input biases read in place: a column slice (row stride > C) and a [C] row
        for cl in (False, True):
            x = torch.randn(n, c, h, w, device="cuda", dtype=torch.bfloat16)
            x = (x.contiguous(memory_format=torch.channels_last) if cl else x).requires_grad_()
            wide = torch.randn(n, c + 24, device="cuda")
            for ib in (wide[:, 16:16 + c], wide[0, :c]):
                group_norm(x, g, None, None, 1e-6, True, input_bias=ib).float().sum().backward()
    torch.cuda.synchronize()
    print("ok strided input bias", flush=True)
    for n, c, h, w, g in ((4, 512, 8, 8, 32), (16, 320, 5, 5, 32), (8, 128, 9, 9, 32)):  # one-launch input gradient
        for dtype in (torch.float32, torch.bfloat16):
            x = torch.randn(n, c, h, w, device="cuda", dtype=dtype).contiguous(memory_format=torch.channels_last)
            wt, b = torch.randn(c, device="cuda", dtype=dtype), torch.randn(c, device="cuda", dtype=dtype)
            gy, res = torch.randn_like(x), torch.randn_like(x)
            ib = torch.randn(n, c + 8, device="cuda")[:, 8:]
            for silu in (False, True):
                _, mean, rstd = group_norm_with_stats(x, g, wt, b, 1e-6, silu, ib)
                dx = group_norm_input_grad(gy, x, g, mean, rstd, wt, b, silu, ib, res)
                assert bool(torch.isfinite(dx.float()).all())
    torch.cuda.synchronize()
    print("ok one-launch input gradient", flush=True)
    for n, c, h, w, _ in SHAPES:  # channel_bias_add: vector and scalar paths, both layouts, unaligned
        for dtype in (torch.float32, torch.bfloat16, torch.float16):
            x = torch.randn(n, c, h, w, device="cuda", dtype=dtype)
            b = torch.randn(c, device="cuda", dtype=dtype)
            bn = torch.randn(n, c, device="cuda", dtype=dtype)
            for t in (x, x.contiguous(memory_format=torch.channels_last)):
                assert torch.equal(channel_bias_add(t, b), t + b[None, :, None, None])
                r = torch.randn_like(t)  # per-sample bias and residual: the folded ResNet adds
                want = ((t.float() + bn.float()[:, :, None, None]) + r.float()).to(dtype)
                assert torch.equal(channel_bias_add(t, bn, r), want)
    base = torch.randn(1 + 2 * 30 * 5 * 7, device="cuda", dtype=torch.bfloat16)
    xu = base[1:].view(2, 30, 5, 7)
    assert torch.equal(channel_bias_add(xu, base[:30]), xu + base[:30, None, None])
    torch.cuda.synchronize()
    print("ok channel_bias_add", flush=True)


if __name__ == "__main__":
    main()
