"""GroupNorm on every map shape of the CSD step's UNets and VAE, one op at a time: tiger's
``group_norm`` (32 groups, SiLU, affine, a per-(sample, channel) input bias; bfloat16,
channels-last, as the guidance runs it), microseconds per call from 50 calls replayed as one CUDA
graph. Forward shapes: MVDream's UNet (2 branches x 4 views = 8 rows) at 4²-32², InstructPix2Pix's
(12 rows) at 8²-64², the VAE encoder's 4 views at 32²-128², including the up blocks' 1920- and
2560-channel concatenations. Backward (``group_norm_input_grad``: the VAE encoder's input
gradient, the only GroupNorm backward of an SDS step): the encoder's maps at 32²-512², with SiLU,
and with a residual gradient as its ResNet blocks pass one. Which kernels a shape takes (the
one-launch forward, the three-kernel walk and its column passes) is in csrc/group_norm.
Usage: python -m benchmarks.gpu.group_norm_maps [--tag NAME] [--no-forward] [--no-backward]"""
from __future__ import annotations

import argparse

import torch

from benchmarks.common import cuda_graph_ms
from benchmarks.group_norm import VAE_SHAPES
from tiger.ops.group_norm import group_norm, group_norm_input_grad, group_norm_with_stats

# (rows, channels, height, width)
SHAPES = [(8, 1280, 4, 4), (8, 1280, 8, 8), (8, 2560, 8, 8), (8, 640, 16, 16), (8, 1920, 16, 16),
          (8, 320, 32, 32), (4, 512, 32, 32), (12, 1280, 8, 8), (12, 2560, 8, 8), (12, 1280, 16, 16),
          (12, 1920, 16, 16), (12, 640, 32, 32), (12, 320, 64, 64), (4, 512, 64, 64), (4, 256, 128, 128),
          (4, 512, 128, 128), (4, 256, 256, 256), (4, 128, 512, 512)]

# the VAE encoder's backward maps (4 views): MVDream's 32², 128² and 256² maps, then benchmarks.group_norm's
# InstructPix2Pix maps, smallest first (rows, channels, height, width)
BACKWARD_SHAPES = [(4, 512, 32, 32), (4, 256, 128, 128), (4, 128, 256, 256), *reversed(VAE_SHAPES)]


def _inputs(n: int, c: int, h: int, w: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """A bf16 channels-last [n, c, h, w] map, its [c] weight (also the bias) and [n, c] input bias."""
    x = torch.randn(n, c, h, w, device="cuda").bfloat16().contiguous(memory_format=torch.channels_last)
    return x, torch.rand(c, device="cuda").bfloat16(), torch.randn(n, c, device="cuda")


def time_shape(n: int, c: int, h: int, w: int, calls: int = 50) -> float:
    """Microseconds per forward call of one [n, c, h, w] map (graph replays)."""
    x, weight, input_bias = _inputs(n, c, h, w)
    return 1e3 * cuda_graph_ms(lambda: group_norm(x, 32, weight, weight, 1e-5, True, input_bias=input_bias),
                               calls=calls)


def time_backward(n: int, c: int, h: int, w: int, residual: bool, calls: int = 50) -> float:
    """Microseconds per input-gradient call of one [n, c, h, w] map (SiLU; graph replays)."""
    x, weight, input_bias = _inputs(n, c, h, w)
    dy = torch.randn_like(x)
    res = torch.randn_like(x) if residual else None
    _, mean, rstd = group_norm_with_stats(x, 32, weight, weight, 1e-5, True, input_bias=input_bias)
    return 1e3 * cuda_graph_ms(lambda: group_norm_input_grad(dy, x, 32, mean, rstd, weight, weight, True, input_bias,
                                                             res), calls=calls)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--tag", default="tiger", help="first column of every line (e.g. before / after)")
    p.add_argument("--no-forward", action="store_true")
    p.add_argument("--no-backward", action="store_true")
    args = p.parse_args()
    if not torch.cuda.is_available():
        raise SystemExit("benchmarks.gpu.group_norm_maps: needs a CUDA device")
    for n, c, h, w in [] if args.no_forward else SHAPES:
        print(f"{args.tag} {n}x{c}x{h}x{w} fwd {time_shape(n, c, h, w):.2f} us", flush=True)
    for n, c, h, w in [] if args.no_backward else BACKWARD_SHAPES:
        for residual in (False, True):
            us = time_backward(n, c, h, w, residual)
            print(f"{args.tag} {n}x{c}x{h}x{w} bwd{'+residual' if residual else ''} {us:.2f} us", flush=True)


if __name__ == "__main__":
    main()
