"""cuDNN's 3x3 convolutions at the VAE encoder's and the UNet's shapes (channels-last bf16, cuDNN
autotuning on, one CUDA graph replay per timing): the reference for
``benchmarks/gpu/cutlass_conv_probe.cu`` in the same call (raw
``benchmarks/gpu/results/cutlass_conv_vs_cudnn_h100.txt``).

    python -m benchmarks.gpu.cudnn_conv_time          # CUDA only
"""
from __future__ import annotations

import torch
import torch.nn.functional as F

from benchmarks.common import cuda_graph_ms

#: (N, H, W, C, K): the VAE encoder's 512², 256², 128² levels and the InstructPix2Pix UNet's 64².
SHAPES = [(4, 512, 512, 128, 128), (4, 256, 256, 256, 256), (4, 128, 128, 512, 512), (12, 64, 64, 320, 320)]


def main() -> int:
    if not torch.cuda.is_available():
        raise SystemExit("benchmarks.gpu.cudnn_conv_time needs CUDA")
    torch.backends.cudnn.benchmark = True
    for n, h, w, c, k in SHAPES:
        x = torch.randn(n, c, h, w, device="cuda", dtype=torch.bfloat16).contiguous(memory_format=torch.channels_last)
        wt = (torch.randn(k, c, 3, 3, device="cuda", dtype=torch.bfloat16) * 0.05).contiguous(
            memory_format=torch.channels_last)
        ms = cuda_graph_ms(lambda: F.conv2d(x, wt, padding=1))
        flop = 2 * n * h * w * k * 9 * c
        print(f"cuDNN {n}x{h}x{w}x{c}->{k}: {ms:.4f} ms  {flop / ms / 1e9:.0f} TFLOP/s")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
