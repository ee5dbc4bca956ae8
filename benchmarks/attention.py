"""tiger::attention_rows (every schedule and CTA size on the GPU) against torch's SDPA (the peer:
cuDNN's fused attention on an H100, the math path on the CPU) on the guidances' self-attention
shapes: ms per call and the relative error against the float64 definition
(tests/ops/test_attention.py), plus the exponential bound (one exp per score at the SFU's rate,
`exp2_throughput_h100.txt`) and the FLOP bound at head dim 40.

    python -m benchmarks.attention                 # CPU, a small shape
    python -m benchmarks.attention --device cuda   # InstructPix2Pix's 64² layers (batch 12 and 8)

GPU times are CUDA-graph replays (as the guidance step runs them) of 10 calls, median of 20.
"""
from __future__ import annotations

import argparse

import torch

from benchmarks.common import cpu_time_ms, cuda_graph_ms, rel_err
from tests.ops.test_attention import attention64, sdpa_rows, stacked_qkv
from tiger.ops.attention import SCHEDULES, attention_rows

SFU_EXP_PER_S = 4.16e12  # H100, measured (benchmarks/gpu/results/exp2_throughput_h100.txt)
TENSOR_FLOP_PER_S = 790e12  # H100 bf16 dense GEMM rate measured in this project


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--device", default="cpu", choices=["cpu", "cuda"])
    p.add_argument("--shapes", default=None, help="batch x L x heads, comma-separated (default per device)")
    args = p.parse_args()
    cuda = args.device == "cuda"
    shapes = args.shapes or ("12x4096x8,8x4096x8" if cuda else "2x512x8")
    dtype = torch.bfloat16 if cuda else torch.float32
    print(f"# python -m benchmarks.attention --device {args.device}; "
          f"{torch.cuda.get_device_name() if cuda else 'CPU'}; {dtype}, head dim 40")
    print(f"{'batch x L x heads':>18} {'who':>22} {'ms':>8} {'rel. error':>11} {'x exp bound':>12} {'x FLOP bound':>13}")
    for spec in shapes.split(","):
        batch, L, heads = (int(x) for x in spec.split("x"))
        g = torch.Generator().manual_seed(0)
        q, k, v = stacked_qkv(batch, L, heads, 40, dtype, args.device, g)
        ref = attention64(q, k, v, batch, heads)
        exp_ms = batch * heads * L * L / SFU_EXP_PER_S * 1e3
        flop_ms = 4 * batch * heads * L * L * 40 / TENSOR_FLOP_PER_S * 1e3
        runs = [("torch SDPA (peer)", lambda: sdpa_rows(q, k, v, batch, heads))]
        variants = [(k_, w) for k_, ws in SCHEDULES.items() for w in ws] if cuda else [("producer", 3)]
        for k_, w in variants:
            runs.append((f"tiger, {k_} x{w}" if cuda else "tiger (reference)",
                         lambda k_=k_, w=w: attention_rows(q, k, v, batch, heads, schedule=k_, warpgroups=w)))
        with torch.no_grad():
            for who, fn in runs:
                ms = cuda_graph_ms(fn, calls=10) if cuda else cpu_time_ms(fn)
                err = rel_err(fn(), ref)
                bounds = f"{ms / exp_ms:>12.2f} {ms / flop_ms:>13.2f}" if cuda else f"{'':>12} {'':>13}"
                print(f"{spec:>18} {who:>22} {ms:>8.3f} {err:>11.2e} {bounds}")


if __name__ == "__main__":
    main()
