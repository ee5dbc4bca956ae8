"""The InstructPix2Pix UNet's self-attention shapes through torch's SDPA with cuDNN's and flash
kernels, at head dim 40 (the model's), 48 and 64 (zero-padded choices a hand-written kernel might
take) and the 32² layers' 80: whether padding the head dim costs cuDNN anything, and the reference
for a CUTLASS FMHA probe in the same call (raw ``benchmarks/gpu/results/fmha_cutlass_vs_cudnn_h200.txt``).
One CUDA graph replay per timing (``benchmarks.common.cuda_graph_ms``), median of 20.

    python -m benchmarks.gpu.sdpa_head_dims          # CUDA only
"""
from __future__ import annotations

import torch
import torch.nn.functional as F

from benchmarks.common import cuda_graph_ms

#: (batch, heads, tokens, head dim): 12 = 3 guidance branches x 4 views.
SHAPES = [(12, 8, 4096, 40), (12, 8, 4096, 48), (12, 8, 4096, 64), (12, 8, 1024, 80)]


def main() -> int:
    if not torch.cuda.is_available():
        raise SystemExit("benchmarks.gpu.sdpa_head_dims needs CUDA")
    from torch.nn.attention import SDPBackend, sdpa_kernel

    for B, H, L, d in SHAPES:
        q, k, v = (torch.randn(B, H, L, d, device="cuda", dtype=torch.bfloat16) for _ in range(3))
        row = []
        for name, backend in (("cudnn", SDPBackend.CUDNN_ATTENTION), ("flash", SDPBackend.FLASH_ATTENTION)):
            try:
                with sdpa_kernel([backend]):
                    ms = cuda_graph_ms(lambda: F.scaled_dot_product_attention(q, k, v))
                row.append(f"{name} {ms:.3f} ms ({4 * B * H * L * L * d / ms / 1e9:.0f} TFLOP/s at d={d})")
            except RuntimeError as e:  # a backend that refuses the shape
                row.append(f"{name} n/a ({type(e).__name__})")
        print(f"SDPA B={B} H={H} L={L} d={d}: " + "; ".join(row))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
