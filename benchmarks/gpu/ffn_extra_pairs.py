"""The fused transformer block's feed-forward GEMMs with and without its 8 extra GEGLU pairs
(:mod:`tiger.edit.guidance.transformer_blocks`): the projection at N = 2F against 2(F + 8), the
output accumulated into the residual stream (``addmm_``) at K = F against F + 8, on the rows and
widths of InstructPix2Pix's (batch 12) and MVDream's (batch 8) transformer levels, bf16; per shape
the best of 5 replays of a CUDA graph of 50 calls (raw
``benchmarks/gpu/results/ffn_extra_pairs_gemm_h100.txt``). What a carrying transformer's last
block saves by leaving its biases to ``proj_out``.

    python -m benchmarks.gpu.ffn_extra_pairs          # CUDA only
"""
from __future__ import annotations

from typing import Callable

import torch
import torch.nn.functional as F

#: (label, token rows, channels C): F = 4C, the GEGLU projection 2F wide.
LEVELS = [("ip2p 64^2", 49152, 320), ("ip2p 32^2", 12288, 640), ("ip2p 16^2", 3072, 1280), ("ip2p 8^2", 768, 1280),
          ("mvdream 32^2", 8192, 320), ("mvdream 16^2", 2048, 640), ("mvdream 8^2", 512, 1280)]
EXTRA = 8


def graph_best_ms(fn: Callable[[], object], calls: int = 50, replays: int = 5) -> float:
    """ms per call: the best of ``replays`` replays of a graph of ``calls`` calls (after 5 eager ones)."""
    for _ in range(5):
        fn()
    torch.cuda.synchronize()
    graph, side = torch.cuda.CUDAGraph(), torch.cuda.Stream()
    side.wait_stream(torch.cuda.current_stream())
    with torch.cuda.stream(side):
        fn()
        with torch.cuda.graph(graph):
            for _ in range(calls):
                fn()
    torch.cuda.current_stream().wait_stream(side)
    torch.cuda.synchronize()
    best = float("inf")
    for _ in range(replays):
        start, end = torch.cuda.Event(enable_timing=True), torch.cuda.Event(enable_timing=True)
        start.record()
        graph.replay()
        end.record()
        torch.cuda.synchronize()
        best = min(best, start.elapsed_time(end) / calls)
    return best


def main() -> int:
    if not torch.cuda.is_available():
        raise SystemExit("benchmarks.gpu.ffn_extra_pairs needs CUDA")
    dt = torch.bfloat16
    for label, rows, c in LEVELS:
        f = 4 * c
        x = torch.randn(rows, c, device="cuda", dtype=dt)
        us = {}
        for extra in (0, EXTRA):
            n = 2 * (f + extra)
            w = torch.randn(n, c, device="cuda", dtype=dt) * 0.05
            bias = torch.randn(n, device="cuda", dtype=dt)
            w_out = torch.randn(c, f + extra, device="cuda", dtype=dt) * 0.02
            g = torch.randn(rows, f + extra, device="cuda", dtype=dt)
            h = torch.randn(rows, c, device="cuda", dtype=dt)
            us[extra, "proj"] = 1e3 * graph_best_ms(lambda: F.linear(x, w, bias))
            us[extra, "out"] = 1e3 * graph_best_ms(lambda: h.addmm_(g, w_out.t()))
        print(f"{label:14s} rows {rows:6d} C {c:5d}: proj N={2 * f}: {us[0, 'proj']:7.1f} us, "
              f"N={2 * (f + EXTRA)}: {us[EXTRA, 'proj']:7.1f} us | out addmm_ K={f}: {us[0, 'out']:7.1f} us, "
              f"K={f + EXTRA}: {us[EXTRA, 'out']:7.1f} us", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
