"""Every cuDNN execution plan for the guidance UNets' self-attention shapes (bf16 forward, ms),
against torch's SDPA (which picks cuDNN's on the H100): does another engine, or the head dim
zero-padded from 40 to 48, beat the default at InstructPix2Pix's 64² layers? Needs the cuDNN
frontend's Python package (``nvidia-cudnn-frontend`` from PyPI, not a tiger dependency: pass the
folder it is installed in with ``--frontend``); torch's own cuDNN library is used.

    pip install --no-deps --target /tmp/cfe nvidia-cudnn-frontend
    python -m benchmarks.gpu.sdpa_cudnn_plans --frontend /tmp/cfe        # CUDA only
"""
from __future__ import annotations

import argparse
import sys

import torch
import torch.nn.functional as F

from benchmarks.gpu.sdpa_backends import time_ms

SHAPES = {"ip2p self 64^2": (12, 8, 4096, 40), "ip2p self 32^2": (12, 8, 1024, 80),
          "mvdream mv-self 4x32^2": (2, 5, 4096, 64)}  # batch, heads, tokens, head dim


def unet_layout(b: int, h: int, n: int, d: int) -> torch.Tensor:
    """[b, h, n, d] bf16 viewed from [b, n, h·d] token rows, the strides the UNets' SDPA sees."""
    return torch.randn(b, n, h * d, device="cuda", dtype=torch.bfloat16).view(b, n, h, d).transpose(1, 2)


def plan_times(cudnn, handle, q, k, v, d: int, ref: torch.Tensor) -> list[tuple[float, float]]:
    """(ms, max error vs float32) of every plan cuDNN's heuristics A, B and fallback offer."""
    dp = q.shape[-1]
    b, h, n, _ = q.shape
    o = torch.empty(b, n, h, dp, device="cuda", dtype=torch.bfloat16).transpose(1, 2)
    g = cudnn.pygraph(io_data_type=cudnn.data_type.BFLOAT16, intermediate_data_type=cudnn.data_type.FLOAT,
                      compute_data_type=cudnn.data_type.FLOAT, handle=handle)
    tq, tk, tv = g.tensor_like(q), g.tensor_like(k), g.tensor_like(v)
    try:
        to, _ = g.sdpa(name="sdpa", q=tq, k=tk, v=tv, generate_stats=False, attn_scale=d ** -0.5, use_causal_mask=False)
    except TypeError:  # older frontends
        to, _ = g.sdpa(name="sdpa", q=tq, k=tk, v=tv, is_inference=True, attn_scale=d ** -0.5, use_causal_mask=False)
    to.set_output(True).set_dim(list(o.shape)).set_stride(list(o.stride()))
    g.validate()
    g.build_operation_graph()
    g.create_execution_plans([cudnn.heur_mode.A, cudnn.heur_mode.B, cudnn.heur_mode.FALLBACK])
    out = []
    for i in range(g.get_execution_plan_count()):
        g.build_plan_at_index(i)
        ws = torch.empty(max(1, g.get_workspace_size_plan_at_index(i)), device="cuda", dtype=torch.uint8)
        pack = {tq: q, tk: k, tv: v, to: o}
        ms = time_ms(lambda: g.execute_plan_at_index(pack, ws, i, handle=handle), n=40)
        out.append((ms, float((o[..., :d].float() - ref).abs().max())))
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frontend", default=None, help="folder holding the cudnn frontend package")
    args = ap.parse_args()
    if args.frontend:
        sys.path.insert(0, args.frontend)
    import cudnn  # noqa: E402  (the optional frontend, after torch loaded its cuDNN)

    handle = cudnn.create_handle()
    cudnn.set_stream(handle, torch.cuda.current_stream().cuda_stream)
    print(f"# {torch.cuda.get_device_name()}, cuDNN backend {cudnn.backend_version()}, torch {torch.__version__}")
    for name, (b, h, n, d) in SHAPES.items():
        q, k, v = (unet_layout(b, h, n, d) for _ in range(3))
        ref = F.scaled_dot_product_attention(q.float(), k.float(), v.float())
        ms = time_ms(lambda: F.scaled_dot_product_attention(q, k, v), n=40)
        err = float((F.scaled_dot_product_attention(q, k, v).float() - ref).abs().max())
        print(f"== {name} (batch {b}, {h} heads, {n} tokens, head dim {d}): torch SDPA {ms:.3f} ms, error {err:.2e}")
        for dp in sorted({d, (d + 15) // 16 * 16}):
            padded = [F.pad(x, (0, dp - d)) if dp != d else x for x in (q, k, v)]
            for i, (pms, perr) in enumerate(plan_times(cudnn, handle, *padded, d, ref)):
                print(f"   head dim {dp}, plan {i}: {pms:.3f} ms, error {perr:.2e}")


if __name__ == "__main__":
    main()
