"""tiger's row softmax (:func:`tiger.ops.softmax.softmax_rows`) against torch's softmax, forward
and backward, on the VAE attention's score shapes: InstructPix2Pix's 4 renders at 512² (4 x
4096 rows of 4096) and MVDream's at 256² (4 x 1024 rows of 1024), bf16 (and float32 for the
first). Per op: GPU time of a CUDA graph of 20 calls (:func:`benchmarks.common.cuda_graph_ms`),
its bytes at the copy bandwidth measured in the same run (the floor: forward reads the scores and
writes the probabilities, backward reads the probabilities and their gradient and writes the
scores' gradient), and the largest error against float64 in units of the output's ulp at 1
(finfo.eps). The CPU has no row kernel of its own (the op is torch's softmax there).

    python -m benchmarks.gpu.softmax_rows          # CUDA only
"""
from __future__ import annotations

import torch

from benchmarks.common import cuda_copy_bandwidth, cuda_graph_ms, print_table
from tests.ops.test_softmax import reference, reference_backward
from tiger.ops.softmax import softmax_rows

SHAPES = [("ip2p vae 512^2", (4, 4096, 4096), torch.bfloat16), ("mvdream vae 256^2", (4, 1024, 1024), torch.bfloat16),
          ("ip2p vae 512^2 fp32", (4, 4096, 4096), torch.float32)]


def _max_error(got: torch.Tensor, want: torch.Tensor, dtype: torch.dtype) -> float:
    """Largest |got - want| over the first 64 rows in units of ``dtype``'s eps (want float64)."""
    return float((got[:64].cpu().double() - want).abs().max()) / torch.finfo(dtype).eps


def main() -> int:
    if not torch.cuda.is_available():
        raise SystemExit("benchmarks.gpu.softmax_rows needs CUDA")
    bandwidth = cuda_copy_bandwidth()
    rows = []
    for label, shape, dt in SHAPES:
        g = torch.Generator(device="cuda").manual_seed(0)
        x = (torch.randn(shape, device="cuda", generator=g) * 4).to(dt)
        gy = torch.randn(shape, device="cuda", generator=g).to(dt)
        x64, gy64 = x.reshape(-1, shape[-1])[:64].cpu(), gy.reshape(-1, shape[-1])[:64].cpu()
        y_ref = reference(x64)
        nbytes = x.numel() * x.element_size()
        for name, fwd, bwd in (
                ("torch", lambda: torch.softmax(x, -1),
                 lambda y: torch.ops.aten._softmax_backward_data(gy, y, -1, dt)),
                ("tiger", lambda: softmax_rows(x), lambda y: torch.ops.tiger.softmax_rows_backward(y, gy))):
            y = fwd()
            dx = bwd(y)
            dx_ref = reference_backward(y.reshape(-1, shape[-1])[:64].cpu(), gy64)
            fwd_ms = cuda_graph_ms(fwd, calls=20)  # per call
            bwd_ms = cuda_graph_ms(lambda: bwd(y), calls=20)
            rows.append({"shape": label, "op": name, "forward_ms": fwd_ms, "forward_floor_ms": 2e3 * nbytes / bandwidth,
                         "forward_err_eps": _max_error(y.reshape(-1, shape[-1]), y_ref, dt),
                         "backward_ms": bwd_ms, "backward_floor_ms": 3e3 * nbytes / bandwidth,
                         "backward_err_eps": _max_error(dx.reshape(-1, shape[-1]), dx_ref, dt)})
    print(f"# {torch.cuda.get_device_name()}: copy bandwidth {bandwidth / 1e12:.2f} TB/s (read + write)")
    print_table(rows, "softmax over the last dim: GPU ms per call (graph of 20), floor = bytes at the copy rate, "
                      "largest error vs float64 in eps of the dtype")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
