"""torch's SDPA (cuDNN and flash backends) on InstructPix2Pix's 64² self-attention (batch 12 and 8 x 8
heads x 4096 tokens, head dim 40, strided q/k/v of one stacked matrix), timed as
benchmarks/gpu/attention_probe.cu times tiger's kernel: eager calls, best of 6 runs of 20 by CUDA
events. With ``ncu`` as argument, only three cuDNN calls at batch 12 (for Nsight Compute). H100.

    python -m benchmarks.gpu.sdpa_event_time [ncu]
"""
from __future__ import annotations

import sys

import torch
from torch.nn.attention import SDPBackend, sdpa_kernel

from tests.ops.test_attention import stacked_qkv

BACKENDS = (("cudnn", SDPBackend.CUDNN_ATTENTION), ("flash", SDPBackend.FLASH_ATTENTION))


def qkv(batch: int, heads: int = 8, L: int = 4096, D: int = 40):
    """q, k, v [batch, heads, L, D] bf16: views of the strided column blocks of one stacked
    [batch·L, 3·heads·D] matrix (tests/ops/test_attention.stacked_qkv), as the UNets hold them."""
    rows = stacked_qkv(batch, L, heads, D, torch.bfloat16, "cuda", torch.Generator().manual_seed(batch))
    return [t.view(batch, L, heads, D).transpose(1, 2) for t in rows]


def best_ms(fn, runs: int = 7, calls: int = 20) -> float:
    for _ in range(3):
        fn()
    torch.cuda.synchronize()
    e0, e1 = torch.cuda.Event(enable_timing=True), torch.cuda.Event(enable_timing=True)
    best = float("inf")
    for run in range(runs):
        e0.record()
        for _ in range(calls):
            fn()
        e1.record()
        torch.cuda.synchronize()
        if run:  # the first run warms the clocks
            best = min(best, e0.elapsed_time(e1) / calls)
    return best


def main() -> None:
    if sys.argv[1:] == ["ncu"]:
        q, k, v = qkv(12)
        with sdpa_kernel(SDPBackend.CUDNN_ATTENTION):
            for _ in range(3):
                torch.nn.functional.scaled_dot_product_attention(q, k, v)
        torch.cuda.synchronize()
        return
    for batch in (12, 8):
        q, k, v = qkv(batch)
        for name, backend in BACKENDS:
            try:
                with sdpa_kernel(backend):
                    ms = best_ms(lambda: torch.nn.functional.scaled_dot_product_attention(q, k, v))
                print(f"torch SDPA {name:<6} B={batch}  {ms:.4f} ms")
            except RuntimeError as e:  # a backend that does not take this shape or device
                print(f"torch SDPA {name} B={batch}: not available ({str(e).splitlines()[0][:100]})")


if __name__ == "__main__":
    main()
