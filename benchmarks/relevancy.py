"""Relevancy op (fused normalise + cosine + LERF relevancy) throughput and error.

Rows: N Gaussians x 64-d embeddings (fp16 / fp32 / fp64), one query, the 4 canonical negatives.
Columns: the op's time, effective bandwidth (bytes the op must move: features once, outputs once),
the bandwidth floor (those bytes at the device's measured copy bandwidth) and the ratio to it,
the time of the same computation in eager PyTorch, and the max error of cosine and relevancy
against a float64 reference.

    python -m benchmarks.relevancy                  # CPU
    python -m benchmarks.relevancy --device cuda    # GPU, 1e6 .. 1e7 (acceptance: fp16 1e7 <= 2x floor)
"""
from __future__ import annotations

import argparse

import torch

from benchmarks.common import median_time, print_table  # noqa: E402

import tiger  # noqa: E402,F401


def reference(f: torch.Tensor, q: torch.Tensor, n: torch.Tensor, t: float = 10.0):
    """Eager PyTorch in f's precision (float64 in, float64 reference)."""
    fh = torch.nn.functional.normalize(f.to(q.dtype) if f.dtype == torch.float16 else f, dim=1)
    cos = fh @ torch.nn.functional.normalize(q, dim=1).T.to(fh.dtype)
    neg = fh @ torch.nn.functional.normalize(n, dim=1).T.to(fh.dtype)
    rel = torch.sigmoid(t * (cos - neg.amax(dim=1, keepdim=True)))
    return cos, rel


def copy_bandwidth(device: str) -> float:
    """Measured device copy bandwidth in bytes/s (read + write of a 1 GiB buffer; CPU: 256 MiB)."""
    n = (1 << 30 if device == "cuda" else 1 << 28) // 4
    x = torch.empty(n, dtype=torch.float32, device=device).uniform_()
    y = torch.empty_like(x)
    t = median_time(lambda: y.copy_(x), repeats=5, warmup=2, cuda=device == "cuda")
    return 2 * x.numel() * 4 / t


def run(device: str, sizes: list[int], dtypes: list[torch.dtype], d: int = 64, q: int = 1, m: int = 4) -> list[dict]:
    cuda = device == "cuda"
    bw = copy_bandwidth(device)
    print(f"# device {torch.cuda.get_device_name() if cuda else 'cpu'}; measured copy bandwidth "
          f"{bw / 1e9:.1f} GB/s; threads {torch.get_num_threads()}", flush=True)
    rows = []
    g = torch.Generator().manual_seed(0)
    pos = torch.randn(q, d, generator=g).to(device)
    neg = torch.randn(m, d, generator=g).to(device)
    for n in sizes:
        torch.manual_seed(n)
        base = torch.randn(n, d, device=device)
        for dt in dtypes:
            f = base.to(dtype=dt)
            op = lambda: torch.ops.tiger.relevancy(f, pos, neg, 10.0, 1e-12)  # noqa: E731
            t_op = median_time(op, repeats=7 if cuda else 3, warmup=2 if cuda else 1, cuda=cuda)
            t_eager = median_time(lambda: reference(f, pos, neg), repeats=3, warmup=1, cuda=cuda)
            cos, rel = op()
            # Errors against float64 on a slice (the whole 1e7 in float64 would dominate the run).
            k = min(n, 200_000)
            rc, rr = reference(f[:k].double(), pos.double(), neg.double())
            out_bytes = cos.element_size() * n * q * 2
            nbytes = f.numel() * f.element_size() + out_bytes
            floor = nbytes / bw
            rows.append({"N": n, "dtype": str(dt).replace("torch.", ""), "op_ms": 1e3 * t_op,
                         "GB/s": nbytes / t_op / 1e9, "floor_ms": 1e3 * floor, "x_floor": t_op / floor,
                         "eager_ms": 1e3 * t_eager, "speedup": t_eager / t_op,
                         "cos_err": float((cos[:k].double() - rc).abs().max()),
                         "rel_err": float((rel[:k].double() - rr).abs().max())})
            del f, cos, rel
        del base
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--device", default="cpu", choices=("cpu", "cuda"))
    ap.add_argument("--sizes", type=float, nargs="*", default=None)
    args = ap.parse_args()
    if args.device == "cuda" and not (torch.cuda.is_available() and tiger.ops.cuda_enabled()):
        raise SystemExit("benchmarks/relevancy.py: --device cuda needs a GPU and tiger built with CUDA")
    sizes = [int(s) for s in args.sizes] if args.sizes else (
        [1_000_000, 3_000_000, 10_000_000] if args.device == "cuda" else [10_000, 100_000, 1_000_000])
    rows = run(args.device, sizes, [torch.float16, torch.float32, torch.float64])
    print_table(rows, title=f"relevancy op, D=64, Q=1, M=4, {args.device}")
    if args.device == "cuda":
        big = [r for r in rows if r["dtype"] == "float16" and r["N"] == max(sizes)]
        if big:
            ok = big[0]["x_floor"] <= 2.0
            print(f"ACCEPTANCE fp16 N={max(sizes)}: {big[0]['x_floor']:.2f}x the bandwidth floor "
                  f"-> {'PASS' if ok else 'FAIL'} (<= 2x)")


if __name__ == "__main__":
    main()
