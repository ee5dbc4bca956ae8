"""A small CUDA workload of tiger::jittered_window_attention for compute-sanitizer (memcheck /
racecheck): forward and backward of every kernel variant (``WINDOW_VARIANTS``) in float32 and
float64 (the bf16 variant in float32 only), on a tiny odd geometry, an even channel count, the
fit's kernel 29 with 129 channels and FeatUp jitters, and zoom < 1 copies whose footprints
overflow the tile (NaN path: every cell, or some cells of a row). Each variant's result is checked against the baseline kernels.

    PYTORCH_NO_CUDA_MEMORY_CACHING=1 compute-sanitizer --tool memcheck --error-exitcode 99 \\
        python -m benchmarks.gpu.sanitize_window_attention
"""
from __future__ import annotations

import torch

import tiger
from tiger.language.featup import sample_jitter
from tiger.language.featup_fit import jitter_coords, jitter_params, reflect_coords, window_geometry
from tiger.ops.featup import WINDOW_VARIANTS, jittered_window_attention


def monotone_case(h, w, c, j, size, k, stride, seed=0):
    """Copies one pixel apart at most (zoom >= 1), as tests/language/test_featup_fused.op_args."""
    gen = torch.Generator().manual_seed(seed)
    F = torch.randn(h, w, c, generator=gen, dtype=torch.float64)
    L = torch.randn(h, w, generator=gen, dtype=torch.float64)
    cy = (torch.rand(j, 1, generator=gen, dtype=torch.float64) * 0.5 + torch.arange(h) * 0.8).clamp(max=h - 1)
    cx = (torch.rand(j, 1, generator=gen, dtype=torch.float64) * 0.5 + torch.arange(w) * 0.9).clamp(max=w - 1)
    wk = 1 + 0.3 * torch.randn(k, k, generator=gen, dtype=torch.float64)
    bk = 0.3 * torch.randn(k, k, generator=gen, dtype=torch.float64)
    mask = (torch.rand(j, *size, generator=gen) > 0.3).double()
    return [F, L, cy, cx, wk, bk, mask], stride


def fit_case(h=64, w=112, size=(4, 7), jitters=4, channels=129, kernel=29, seed=0):
    """FeatUp's jitters (reflect pad, zoom up to 1.8, flips) at kernel 29."""
    gen = torch.Generator().manual_seed(seed)
    k, sh, sw, _, _ = window_geometry(h, w, size, kernel)
    max_pad = min(int(round(30 * min(h, w) / 224)), min(h, w) - 1)
    params = jitter_params([sample_jitter(h, w, max_pad, 1.8, True, gen) for _ in range(jitters)], h, w, "cpu")
    sy, sx = jitter_coords(params.double(), h, w)
    F = torch.randn(h, w, channels, generator=gen, dtype=torch.float64)
    L = torch.randn(h, w, generator=gen, dtype=torch.float64)
    wk = 1 + 0.3 * torch.randn(k, k, generator=gen, dtype=torch.float64)
    bk = 0.3 * torch.randn(k, k, generator=gen, dtype=torch.float64)
    mask = (torch.rand(jitters, *size, generator=gen) > 0.2).double()
    return [F, L, reflect_coords(sy, h), reflect_coords(sx, w), wk, bk, mask], (sh, sw)


def run(tensors, stride, variant, dtype, bf16_features=False):
    """out, attn and the four gradients of <out, g> on CUDA; the features rounded to bfloat16
    first when ``bf16_features`` (the baseline on the values that the bf16 variant reads)."""
    F, L, cy, cx, wk, bk, mask = [t.to("cuda", dtype) for t in tensors]
    if bf16_features:
        F = F.to(torch.bfloat16).to(dtype)
    leaves = [t.requires_grad_() for t in (F, L, wk, bk)]
    out, attn = jittered_window_attention(F, L, cy, cx, wk, bk, mask, stride, variant)
    g = torch.randn(out.shape, generator=torch.Generator().manual_seed(1), dtype=torch.float64).to("cuda", dtype)
    grads = torch.autograd.grad((out * g).sum(), leaves)
    torch.cuda.synchronize()
    return [out, attn, *grads]


def main() -> None:
    assert tiger.ops.cuda_enabled() and torch.cuda.is_available()
    overflow, ostride = monotone_case(20, 20, 7, 2, (2, 2), 3, (2, 2))
    overflow[2] = (torch.arange(20.0, dtype=torch.float64) * 4).clamp(max=19).expand(2, 20).contiguous()
    columns, cstride = monotone_case(20, 20, 7, 2, (2, 8), 3, (2, 2))
    x = torch.arange(20.0, dtype=torch.float64)
    columns[3] = torch.where(x < 10, 0.9 * x, 8.1 + 3 * (x - 9)).clamp(max=19).expand(2, 20).contiguous()
    cases = {"tiny": monotone_case(6, 7, 3, 2, (2, 2), 3, (2, 3)),
             "odd": monotone_case(23, 41, 64, 3, (2, 3), 9, (7, 13)),
             "kernel 29": monotone_case(70, 75, 33, 2, (3, 2), 29, (15, 20)),
             "fit jitters": fit_case(),
             "overflow": (overflow, ostride),
             "some columns overflow": (columns, cstride)}
    for name, (tensors, stride) in cases.items():
        for dtype in (torch.float32, torch.float64):
            for variant in WINDOW_VARIANTS:
                if variant.endswith("_bf16") and dtype == torch.float64:
                    continue
                base = run(tensors, stride, "baseline", dtype, bf16_features=variant.endswith("_bf16"))
                new = run(tensors, stride, variant, dtype)
                for a, b in zip(new, base):
                    torch.testing.assert_close(a, b, atol=1e-4, rtol=1e-3, equal_nan=True)
                print(f"ok {name} {dtype} {variant}", flush=True)


if __name__ == "__main__":
    main()
