"""The two passes :mod:`tiger.edit.guidance.skip_concat` and the sub-pixel upsampler run instead of
torch's, on InstructPix2Pix's UNet shapes (batch 12, bf16, channels-last), CUDA only:

* an up block's skip concatenation: ``torch.cat([hidden, skip], 1)`` (what diffusers runs) against
  the skip copied into a wide map whose first channels the producer already wrote
  (:func:`tiger.ops.channel_bias.channel_bias_add` with ``out=`` and no bias: what is left);
* the upsampler's interleave of its four phase outputs with the bias: four strided ``torch.add``
  (the previous code) against :func:`tiger.ops.channel_bias.subpixel_interleave`.

GPU ms per call from a CUDA graph of 20 (:func:`benchmarks.common.cuda_graph_ms`), the floor (bytes
read and written at the copy bandwidth measured in the same run) and the largest difference from
the float64 result (both are exact: 0).

    python -m benchmarks.gpu.skip_concat_ops
"""
from __future__ import annotations

import torch

from benchmarks.common import cuda_copy_bandwidth, cuda_graph_ms, print_table
from tests.ops.test_channel_bias import interleave_reference
from tiger.ops.channel_bias import channel_bias_add, subpixel_interleave

CL = torch.channels_last
#: (hidden channels, skip channels, side) of the up blocks' concatenations, batch 12
CONCATS = [(640, 320, 64), (320, 320, 64), (1280, 640, 32), (640, 640, 32), (1280, 1280, 16), (1280, 640, 16)]
#: (channels, low-resolution side) of the upsamplers, batch 12
UPSAMPLERS = [(1280, 8), (1280, 16), (640, 32)]
N = 12


def main() -> int:
    if not torch.cuda.is_available():
        raise SystemExit("benchmarks.gpu.skip_concat_ops needs CUDA")
    bw = cuda_copy_bandwidth()
    dt = torch.bfloat16
    g = torch.Generator(device="cuda").manual_seed(0)
    rows = []
    for c1, c2, s in CONCATS:
        hidden = torch.randn(N, c1, s, s, device="cuda", generator=g).to(dt).contiguous(memory_format=CL)
        skip = torch.randn(N, c2, s, s, device="cuda", generator=g).to(dt).contiguous(memory_format=CL)
        wide = torch.empty(N, c1 + c2, s, s, device="cuda", dtype=dt, memory_format=CL)
        wide[:, :c1] = hidden
        cat_ms = cuda_graph_ms(lambda: torch.cat([hidden, skip], 1), calls=20)
        copy_ms = cuda_graph_ms(lambda: channel_bias_add(skip, None, out=wide[:, c1:]), calls=20)
        same = torch.equal(wide, torch.cat([hidden, skip], 1))
        rows.append({"concat": f"{N}x({c1}+{c2})x{s}^2", "torch.cat_ms": cat_ms,
                     "cat_floor_ms": 2e3 * wide.numel() * 2 / bw, "skip_copy_ms": copy_ms,
                     "copy_floor_ms": 2e3 * skip.numel() * 2 / bw, "equal": same})
    print(f"# {torch.cuda.get_device_name()}: copy bandwidth {bw / 1e12:.2f} TB/s (read + write)")
    print_table(rows, "up-block skip concatenation: torch.cat vs the skip copied into the producer's wide map")
    rows = []
    for c, s in UPSAMPLERS:
        z = torch.randn(N, 4 * c, s + 1, s + 1, device="cuda", generator=g).to(dt).contiguous(memory_format=CL)
        bias = torch.randn(c, device="cuda", generator=g).to(dt)
        y = torch.empty(N, c, 2 * s, 2 * s, device="cuda", dtype=dt, memory_format=CL)
        zv = z.permute(0, 2, 3, 1).view(N, s + 1, s + 1, 2, 2, c)
        yv = y.permute(0, 2, 3, 1).view(N, s, 2, s, 2, c)

        def four_adds():
            for a in (0, 1):
                for b in (0, 1):
                    torch.add(zv[:, a:a + s, b:b + s, a, b, :], bias, out=yv[:, :, a, :, b, :])

        adds_ms = cuda_graph_ms(four_adds, calls=20)
        four_adds()
        want = interleave_reference(z[:2].cpu(), bias.cpu()).to(dt)
        err_adds = float((y[:2].cpu().double() - want.double()).abs().max())
        one_ms = cuda_graph_ms(lambda: subpixel_interleave(z, bias, out=y), calls=20)
        err_one = float((y[:2].cpu().double() - want.double()).abs().max())
        rows.append({"upsampler": f"{N}x{c}x{s}^2->{2 * s}^2", "four_adds_ms": adds_ms, "four_adds_err": err_adds,
                     "interleave_ms": one_ms, "interleave_err": err_one,
                     "floor_ms": 2e3 * y.numel() * 2 / bw})
    print_table(rows, "sub-pixel upsampling's interleave + bias: four strided adds vs one pass")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
