"""The fused transformer block's feed-forward GEMMs with and without its 8 extra GEGLU pairs
(:mod:`tiger.edit.guidance.transformer_blocks`): the projection at N = 2F against 2(F + 8), the
output accumulated into the residual stream (``addmm_``) at K = F against F + 8, on the rows and
widths of InstructPix2Pix's (batch 12) and MVDream's (batch 8) transformer levels, bf16; per shape
a CUDA graph of 50 calls timed by :func:`benchmarks.common.cuda_graph_ms` (raw
``benchmarks/gpu/results/ffn_extra_pairs_gemm_h100.txt``). What a carrying transformer's last
block saves by leaving its biases to ``proj_out``.

    python -m benchmarks.gpu.ffn_extra_pairs          # CUDA only
"""
from __future__ import annotations

import torch
import torch.nn.functional as F

from benchmarks.common import cuda_graph_ms

#: (label, token rows, channels C): F = 4C, the GEGLU projection 2F wide.
LEVELS = [("ip2p 64^2", 49152, 320), ("ip2p 32^2", 12288, 640), ("ip2p 16^2", 3072, 1280), ("ip2p 8^2", 768, 1280),
          ("mvdream 32^2", 8192, 320), ("mvdream 16^2", 2048, 640), ("mvdream 8^2", 512, 1280)]
EXTRA = 8


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
            us[extra, "proj"] = 1e3 * cuda_graph_ms(lambda: F.linear(x, w, bias), calls=50)
            us[extra, "out"] = 1e3 * cuda_graph_ms(lambda: h.addmm_(g, w_out.t()), calls=50)
        print(f"{label:14s} rows {rows:6d} C {c:5d}: proj N={2 * f}: {us[0, 'proj']:7.1f} us, "
              f"N={2 * (f + EXTRA)}: {us[EXTRA, 'proj']:7.1f} us | out addmm_ K={f}: {us[0, 'out']:7.1f} us, "
              f"K={f + EXTRA}: {us[EXTRA, 'out']:7.1f} us", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
