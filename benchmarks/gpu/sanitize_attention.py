"""A small CUDA workload of tiger::attention_rows for compute-sanitizer (memcheck / racecheck /
synccheck): every schedule and warpgroup count of the head-dim-40 kernel on a length that 64·warpgroups
does not divide (the last CTA's rows past L), strided q/k/v views of one stacked matmul, two heads
and two sequences, each checked against the attention written out in float32 (not SDPA: cuDNN's own
kernel would appear in the sanitizers' reports) so that a silent wrong answer fails too.
"""
from __future__ import annotations

import torch

import tiger  # noqa: F401  (loads the ops)
from tiger.ops.attention import SCHEDULES, attention_rows


def main() -> None:
    batch, heads, L, D = 2, 2, 384, 40
    g = torch.Generator(device="cuda").manual_seed(0)
    qkv = torch.randn(batch * L, 3 * heads * D, device="cuda", dtype=torch.bfloat16, generator=g)
    q, k, v = (qkv[:, i * heads * D:(i + 1) * heads * D] for i in range(3))
    qs, ks, vs = (t.float().view(batch, L, heads, D).transpose(1, 2) for t in (q, k, v))
    weights = torch.softmax(qs @ ks.transpose(-1, -2) / D ** 0.5, dim=-1)
    ref = (weights @ vs).transpose(1, 2).reshape(batch * L, heads * D)
    with torch.no_grad():
        for schedule, counts in SCHEDULES.items():
            for w in counts:
                out = attention_rows(q, k, v, batch, heads, schedule=schedule, warpgroups=w)
                err = ((out.float() - ref.float()).norm() / ref.float().norm()).item()
                print(f"{schedule} x{w}: rel. difference to float32 {err:.2e}")
                assert err < 1e-2, (schedule, w, err)
    torch.cuda.synchronize()


if __name__ == "__main__":
    main()
