"""A small CUDA workload of tiger::attention_rows for compute-sanitizer (memcheck / racecheck /
synccheck): every schedule and warpgroup count of the head-dim-40 kernel on a length that 64·warpgroups
does not divide (the last CTA's rows past L), strided q/k/v views of one stacked matmul, two heads
and two sequences, each checked against the float64 definition (tests/ops/test_attention.attention64;
not SDPA, whose cuDNN kernel would appear in the sanitizers' reports) so that a silent wrong answer
fails too.
"""
from __future__ import annotations

import torch

from tests.ops.test_attention import attention64, stacked_qkv
from tiger.ops.attention import SCHEDULES, attention_rows


def main() -> None:
    batch, heads, L, D = 2, 2, 384, 40
    q, k, v = stacked_qkv(batch, L, heads, D, torch.bfloat16, "cuda", torch.Generator().manual_seed(0))
    ref = attention64(q, k, v, batch, heads)
    with torch.no_grad():
        for schedule, counts in SCHEDULES.items():
            for w in counts:
                out = attention_rows(q, k, v, batch, heads, schedule=schedule, warpgroups=w)
                err = ((out.double() - ref).norm() / ref.norm()).item()
                print(f"{schedule} x{w}: rel. difference to float64 {err:.2e}")
                assert err < 1e-2, (schedule, w, err)
    torch.cuda.synchronize()


if __name__ == "__main__":
    main()
