"""LayerNorm over rows: tiger's ``layer_norm_rows`` against torch's ``F.layer_norm`` on the guidance
UNets' transformer norms, with each one's error against float64 and the memory floor (one read
and one write of the rows at the GPU's bandwidth).

Shapes: InstructPix2Pix's UNet (3 branches x 4 views = 12 samples) at 64², 32², 16², 8² latents
(rows of 320, 640, 1280, 1280 channels; three norms per transformer block, five blocks per
resolution but the 8² one) and MVDream's (2 branches x 4 views) at 32² ... 4²; on the CPU the
same channel counts with 1/16 of the rows. CUDA times are GPU time per call, from 20 calls
replayed as one CUDA graph (as the guidance steps run them).

    python -m benchmarks.layer_norm                         # CPU
    python -m benchmarks.layer_norm --device cuda [--json out.json]
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

import torch
import torch.nn.functional as F

from benchmarks.common import cpu_time_ms, cuda_graph_ms, print_table
from tiger.ops.layer_norm import layer_norm_rows
from tiger.utils.dtypes import DTYPE_NAMES

H100_BYTES_PER_S = 3.35e12
# (model, samples, tokens, channels, norms of that shape in one UNet call)
SHAPES = [("ip2p", 12, 64 * 64, 320, 15), ("ip2p", 12, 32 * 32, 640, 15), ("ip2p", 12, 16 * 16, 1280, 15),
          ("ip2p", 12, 8 * 8, 1280, 3), ("mvdream", 8, 32 * 32, 320, 15), ("mvdream", 8, 16 * 16, 640, 15),
          ("mvdream", 8, 8 * 8, 1280, 15), ("mvdream", 8, 4 * 4, 1280, 3)]


def reference(x, w, b, eps=1e-5):
    xd = x.double()
    mean = xd.mean(-1, keepdim=True)
    return (xd - mean) / torch.sqrt((xd - mean).square().mean(-1, keepdim=True) + eps) * w.double() + b.double()


def rel(y, ref) -> float:
    return float((y.double() - ref).norm() / ref.norm())


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--dtype", default="bf16", choices=sorted(DTYPE_NAMES))
    ap.add_argument("--json", type=Path)
    args = ap.parse_args()
    dev, dtype = torch.device(args.device), DTYPE_NAMES[args.dtype]
    cuda = dev.type == "cuda"
    g = torch.Generator(device=dev).manual_seed(0)
    rows, totals = [], {"ours": 0.0, "ours_shift": 0.0, "torch": 0.0, "floor": 0.0}
    for model, n, tokens, c, count in SHAPES:
        if not cuda:
            tokens = max(1, tokens // 16)
        x = (torch.randn(n, tokens, c, device=dev, generator=g) * 2 + 0.3).to(dtype)
        w = (1 + 0.1 * torch.randn(c, device=dev, generator=g)).to(dtype)
        b = (0.1 * torch.randn(c, device=dev, generator=g)).to(dtype)
        shift = (0.1 * torch.randn(c, device=dev, generator=g)).to(dtype)
        ours = lambda: layer_norm_rows(x, w, b, 1e-5)  # noqa: E731
        # with an input bias, as the fused transformer blocks' second and third norms run
        ours_shift = lambda: layer_norm_rows(x, w, b, 1e-5, input_bias=shift)  # noqa: E731
        theirs = lambda: F.layer_norm(x, (c,), w, b, 1e-5)  # noqa: E731
        timer = (lambda fn: cuda_graph_ms(fn, calls=20)) if cuda else cpu_time_ms
        t_ours, t_shift, t_torch = timer(ours), timer(ours_shift), timer(theirs)
        ref = reference(x, w, b)
        floor = 2 * x.numel() * x.element_size() / H100_BYTES_PER_S * 1e3 if cuda else float("nan")
        rows.append({"model": model, "shape": f"{n}x{tokens}x{c}", "norms": count, "ours_ms": round(t_ours, 4),
                     "ours_shift_ms": round(t_shift, 4), "torch_ms": round(t_torch, 4), "speed-up": round(t_torch / t_ours, 2),
                     "floor_ms": round(floor, 4), "ours_x_floor": round(t_ours / floor, 2) if cuda else None,
                     "ours_err": f"{rel(ours(), ref):.2e}", "torch_err": f"{rel(theirs(), ref):.2e}"})
        for k, v in (("ours", t_ours), ("ours_shift", t_shift), ("torch", t_torch), ("floor", floor)):
            totals[k] += v * count
    name = torch.cuda.get_device_name(dev) if cuda else "CPU"
    print_table(rows, f"LayerNorm rows, {args.dtype}, {name} (ms per call; err: relative to float64)")
    print(f"per UNet call (norms x time): ours {totals['ours']:.3f} ms (all with an input bias "
          f"{totals['ours_shift']:.3f}), torch {totals['torch']:.3f} ms"
          + (f", floor {totals['floor']:.3f} ms (H100 3.35 TB/s)" if cuda else ""))
    if args.json:
        args.json.write_text(json.dumps({"device": name, "rows": rows, "totals_ms": totals}, indent=1))


if __name__ == "__main__":
    main()
