"""FeatUp's implicit network per fit step, forward + backward: the fused network
(``tiger::fourier_layer_norm``: Fourier features, LayerNorm, channel dropout in one op;
``tiger::relu_scale_layer_norm``: the hidden ReLU, dropout and LayerNorm in another) against the
PyTorch composition, eager and replayed from a CUDA graph (as the fast fit runs its step), with
each one's error against the float64 composition; and each fused op alone against the
composition it replaces, with the HBM bandwidth its bytes reach.

    python -m benchmarks.featup_ops                          # CPU, 64 x 112 pixels
    python -m benchmarks.featup_ops --device cuda            # the fit's 256 x 448, bf16 autocast
    python -m benchmarks.featup_ops --device cuda --compile  # also torch.compile'd networks
"""
from __future__ import annotations

import argparse
import contextlib
import copy

import torch

from benchmarks.common import cpu_time_ms, cuda_time_ms, print_table, rel_err
from tiger.language.featup import ImplicitNet, _min_max
from tiger.ops.featup import fourier_layer_norm, relu_scale_layer_norm

H100_HBM_TBPS = 3.35


def autocast(device: torch.device, precision: str):
    if device.type == "cuda" and precision == "bf16":
        return torch.autocast("cuda", dtype=torch.bfloat16, cache_enabled=False)
    return contextlib.nullcontext()


def network_step(net: ImplicitNet, image: torch.Tensor, grad: torch.Tensor, precision: str, compiled=None):
    """One step of the network as the fit runs it: forward under autocast, backward of <out, grad>."""
    forward = compiled or net.forward_pixels

    def step() -> None:
        with autocast(image.device, precision):
            out = forward(image)
        out.float().mul(grad).sum().backward()

    return step


def graphed(step, device: torch.device):
    """``step`` captured once in a CUDA graph (after warm-up steps on a side stream); the replay."""
    side = torch.cuda.Stream(device)
    side.wait_stream(torch.cuda.current_stream(device))
    with torch.cuda.stream(side):
        for _ in range(3):
            step()
    torch.cuda.current_stream(device).wait_stream(side)
    graph = torch.cuda.CUDAGraph()
    with torch.cuda.graph(graph):
        step()
    return graph.replay


def errors(net: ImplicitNet, image: torch.Tensor, grad: torch.Tensor, precision: str) -> dict:
    """Norm-wise relative errors of the output and of three parameter gradients against the
    float64 composition of the same network (evaluation mode: no dropout)."""
    ref = copy.deepcopy(net).double().eval()
    ref.fused = False
    results = []
    for model, img, prec in ((copy.deepcopy(net).eval(), image, precision), (ref, image.double(), "fp32")):
        model.zero_grad(set_to_none=True)
        with autocast(image.device, prec):
            out = model.forward_pixels(img)
        out.double().mul(grad.double()).sum().backward()
        results.append((out.detach(), model.fourier.biases.grad, model.net[0].norm.weight.grad,
                        model.net[2].weight.grad))
    (out, gb, gw, gc), (rout, rgb, rgw, rgc) = results
    return {"err out": rel_err(out, rout), "err grad phase": rel_err(gb, rgb), "err grad ln": rel_err(gw, rgw),
            "err grad conv1": rel_err(gc, rgc)}


def input_layer_rows(net: ImplicitNet, image: torch.Tensor, precision: str, timer) -> list[dict]:
    """The input layers alone (features, LayerNorm, dropout scale, the cast the first linear
    layer makes), forward + backward of <out, g>."""
    dev = image.device
    scaled = _min_max(image)
    b, _, h, w = image.shape
    norm, c = net.net[0].norm, net.fourier.out_dim
    out_dtype = torch.bfloat16 if dev.type == "cuda" and precision == "bf16" else torch.float32
    grad = torch.randn(b, h, w, c, device=dev).to(out_dtype)
    scale = (torch.rand(b, c, device=dev) > 0.2).float() / 0.8
    inputs = net.fourier.pixel_inputs(scaled).reshape(b, h * w, 5)
    freqs = net.fourier.frequencies(dev, torch.float32)

    def composed() -> None:
        x = torch.nn.functional.layer_norm(net.fourier.pixels(scaled), (c,), norm.weight, norm.bias, norm.eps)
        (x * scale.view(b, 1, 1, c)).to(out_dtype).backward(grad)

    def fused() -> None:
        x = fourier_layer_norm(inputs, freqs, net.fourier.biases, norm.weight, norm.bias, scale, norm.eps,
                               None if out_dtype == torch.float32 else out_dtype)
        x.view(b, h, w, c).backward(grad)

    px = h * w
    # the fused op's HBM traffic: the output written and its gradient read (C channels), the
    # inputs read twice, mean/rstd written and read; the parameters' partial sums
    nbytes = px * (2 * c * grad.element_size() + 2 * 5 * 4 + 4 * 4)
    return _timed_pair("input layers", composed, fused, nbytes, dev, timer)


def hidden_layer_rows(net: ImplicitNet, image: torch.Tensor, precision: str, timer) -> list[dict]:
    """The hidden layers alone (ReLU, dropout scale, LayerNorm, as the fit runs them: in the
    first linear layer's output dtype, the composition's LayerNorm in float32 under autocast),
    forward + backward of <out, g>."""
    dev = image.device
    b, _, h, w = image.shape
    norm, d = net.net[5].norm, net.net[5].norm.weight.shape[0]
    act = torch.bfloat16 if dev.type == "cuda" and precision == "bf16" else torch.float32
    x = torch.randn(b, h * w, d, device=dev).to(act).requires_grad_()
    grad = torch.randn(b, h * w, d, device=dev).to(act)
    keep = (torch.rand(b, d, device=dev) > 0.2).float() / 0.8

    def composed() -> None:
        with autocast(dev, precision):
            y = torch.nn.functional.layer_norm(torch.relu(x) * keep.to(act).view(b, 1, d), (d,), norm.weight,
                                               norm.bias, norm.eps)
        y.to(act).backward(grad)

    def fused() -> None:
        relu_scale_layer_norm(x, norm.weight, norm.bias, keep, norm.eps).backward(grad)

    # the fused op's HBM traffic: x read twice, the output written, its gradient read, x's written
    nbytes = b * h * w * (5 * d * x.element_size() + 4 * 4)
    return _timed_pair("hidden layers", composed, fused, nbytes, dev, timer)


def _timed_pair(what: str, composed, fused, nbytes: int, dev: torch.device, timer) -> list[dict]:
    """Rows for the composition and the fused op; on CUDA the fused op's bandwidth against the
    HBM floor of its ``nbytes``."""
    rows = []
    for name, fn in ((f"{what}, composition", composed), (f"{what}, fused", fused)):
        ms = timer(fn)
        row = {"what": name, "ms": ms}
        if fn is fused and dev.type == "cuda":
            row["GB/s"] = nbytes / ms / 1e6
            row["floor ms"] = nbytes / (H100_HBM_TBPS * 1e12) * 1e3
        rows.append(row)
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    ap.add_argument("--size", type=int, nargs=2, default=None, metavar=("H", "W"),
                    help="fitting resolution (default 256 448 on CUDA, 64 112 on CPU)")
    ap.add_argument("--precision", choices=("bf16", "fp32"), default="bf16", help="autocast on CUDA (the fit's)")
    ap.add_argument("--freqs", type=int, default=30)
    ap.add_argument("--dim", type=int, default=128, help="the network's output channels (proj_dim)")
    ap.add_argument("--iters", type=int, default=None, help="timed repetitions (default 50 CUDA, 3 CPU)")
    ap.add_argument("--compile", action="store_true", help="also time torch.compile'd networks")
    args = ap.parse_args()
    dev = torch.device(args.device)
    cuda = dev.type == "cuda"
    h, w = args.size or ((256, 448) if cuda else (64, 112))
    iters = args.iters or (50 if cuda else 3)
    timer = (lambda fn: cuda_time_ms(fn, iters=iters, warmup=5)) if cuda else (lambda fn: cpu_time_ms(fn, iters=iters))
    torch.backends.cuda.matmul.allow_tf32 = True
    gen = torch.Generator().manual_seed(0)
    image = torch.rand(1, 3, h, w, generator=gen).to(dev)
    grad = torch.randn(1, args.dim, h, w, generator=gen).to(dev)
    torch.manual_seed(0)
    base = ImplicitNet(args.dim, args.freqs, gen).to(dev).train()
    print(f"FeatUp implicit network, {h} x {w} = {h * w} pixels, {base.fourier.out_dim} input channels, "
          f"{args.dim} outputs, {args.precision if cuda else 'fp32'} on {dev}"
          + (f" ({torch.cuda.get_device_name(dev)})" if cuda else ""))
    rows = []
    for fused in (False, True):
        for compile_ in ((False, True) if args.compile else (False,)):
            net = copy.deepcopy(base)
            net.fused = fused
            compiled = torch.compile(net.forward_pixels, dynamic=False) if compile_ else None
            step = network_step(net, image, grad, args.precision, compiled)
            name = ("fused" if fused else "composition") + (" + compile" if compile_ else "")
            row = {"network": name, "eager ms": timer(step)}
            if cuda:
                row["graph ms"] = timer(graphed(step, dev))
            row.update(errors(net, image, grad, args.precision))
            rows.append(row)
    print_table(rows, "per step: forward + backward (dropout on); errors against the float64 composition")
    print_table(input_layer_rows(base, image, args.precision, timer) + hidden_layer_rows(base, image, args.precision, timer),
                "each fused op alone against the composition it replaces, forward + backward")


if __name__ == "__main__":
    main()
