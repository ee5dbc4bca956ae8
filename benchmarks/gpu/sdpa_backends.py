"""SDPA backends on the guidance UNets' attention shapes (bf16 forward, ms), against each
shape's FLOP floor at 790 TFLOP/s: IP2P's SD-1.5 UNet at 64² latents (batch 12: 3 branches x
4 views; head dim 40 / 80 / 160) and MVDream's multi-view self-attention (4 views of 32² and 16²).

    python -m benchmarks.gpu.sdpa_backends          # CUDA only
"""
from __future__ import annotations

from typing import Callable

import torch
import torch.nn.functional as F
from torch.nn.attention import SDPBackend, sdpa_kernel


def time_ms(fn: Callable[[], object], n: int = 30) -> float:
    """ms per call over ``n`` calls after 5 warm-up calls (CUDA events)."""
    for _ in range(5):
        fn()
    torch.cuda.synchronize()
    start, end = torch.cuda.Event(enable_timing=True), torch.cuda.Event(enable_timing=True)
    start.record()
    for _ in range(n):
        fn()
    end.record()
    torch.cuda.synchronize()
    return start.elapsed_time(end) / n


SHAPES = [  # name, batch, heads, q tokens, kv tokens, head dim, layers per step
    ("ip2p self 64^2", 12, 8, 4096, 4096, 40, 5), ("ip2p cross 64^2", 12, 8, 4096, 77, 40, 5),
    ("ip2p self 32^2", 12, 8, 1024, 1024, 80, 5), ("ip2p self 16^2", 12, 8, 256, 256, 160, 5),
    ("mvdream mv-self 4x32^2", 3, 5, 4096, 4096, 64, 5), ("mvdream mv-self 4x16^2", 3, 10, 1024, 1024, 64, 5),
]


def main() -> None:
    if not torch.cuda.is_available():
        raise SystemExit("benchmarks.gpu.sdpa_backends needs CUDA")
    backends = {"flash": SDPBackend.FLASH_ATTENTION, "efficient": SDPBackend.EFFICIENT_ATTENTION,
                "cudnn": SDPBackend.CUDNN_ATTENTION, "default": None}
    print(f"{'shape':26s} " + " ".join(f"{b:>10s}" for b in backends) + "   floor ms (790 TF)  x layers")
    for name, b, h, q, k, d, layers in SHAPES:
        Q = torch.randn(b, h, q, d, device="cuda", dtype=torch.bfloat16)
        K = torch.randn(b, h, k, d, device="cuda", dtype=torch.bfloat16)
        V = torch.randn(b, h, k, d, device="cuda", dtype=torch.bfloat16)
        row = []
        for bk in backends.values():
            try:
                if bk is None:
                    ms = time_ms(lambda: F.scaled_dot_product_attention(Q, K, V))
                else:
                    with sdpa_kernel([bk]):
                        ms = time_ms(lambda: F.scaled_dot_product_attention(Q, K, V))
                row.append(f"{ms:10.3f}")
            except RuntimeError:  # a backend that does not take the shape
                row.append(f"{'n/a':>10s}")
        floor = 4 * b * h * q * k * d / 790e12 * 1e3
        print(f"{name:26s} " + " ".join(row) + f"   {floor:8.3f}  x{layers}")


if __name__ == "__main__":
    main()
