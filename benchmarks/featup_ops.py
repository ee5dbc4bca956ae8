"""FeatUp's implicit network per fit step, forward + backward: the fused network
(``tiger::fourier_layer_norm``: Fourier features, LayerNorm, channel dropout in one op;
``tiger::relu_scale_layer_norm``: the hidden ReLU, dropout and LayerNorm in another) against the
PyTorch composition, eager and replayed from a CUDA graph (as the fast fit runs its step), with
each one's error against the float64 composition; and each fused op alone against the
composition it replaces, with the HBM bandwidth its bytes reach. Then the step's block between
the network and the attention op (magnitude, 5-tap reflect blur, logit dropout, the logit map's
1x1 map, the channels-last map the attention op reads): ``tiger::magnitude_blur`` channels last
and ``tiger::masked_logit`` against the channels-first composition they replaced, and
``magnitude_blur`` alone, with errors against float64.
Then ``tiger::jittered_window_attention`` at the fit's geometry (10 jittered copies, kernel 29,
129 channels), forward and forward + backward, with its error against float64.

    python -m benchmarks.featup_ops                          # CPU, 64 x 112 pixels
    python -m benchmarks.featup_ops --device cuda            # the fit's 256 x 448, bf16 autocast
    python -m benchmarks.featup_ops --device cuda --compile  # also torch.compile'd networks
    python -m benchmarks.featup_ops --device cuda --only blur       # only the magnitude + blur block
    python -m benchmarks.featup_ops --device cuda --only attention  # only the attention op
"""
from __future__ import annotations

import argparse
import contextlib
import copy

import torch
import torch.nn.functional as F

from benchmarks.common import cpu_time_ms, cuda_time_ms, print_table, rel_err
from tiger.language.featup import ImplicitNet, _min_max
from tiger.ops.featup import fourier_layer_norm, magnitude_blur, masked_logit, relu_scale_layer_norm
from tiger.utils.filters import gaussian_blur

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


def _blur_composition(x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(blurred [H, W, C + 1], magnitude [H, W]) of x [1, H, W, C] as the step composed them before
    tiger::magnitude_blur: a float32 channels-first copy, norm, cat, depthwise blur, and the
    channels-last copy the attention op reads."""
    hr = x.permute(0, 3, 1, 2).to(torch.promote_types(x.dtype, torch.float32)).contiguous()  # float64 stays
    mag = hr.norm(dim=1, keepdim=True)
    blurred = gaussian_blur(torch.cat([mag, hr], dim=1), 5, 1.0, padding="reflect")
    return blurred[0].permute(1, 2, 0).contiguous(), mag[0, 0]


def blur_rows(dim: int, h: int, w: int, precision: str, dev: torch.device, timer) -> list[dict]:
    """The fit step's block from the network's output to the attention op's inputs, forward +
    backward, composition against tiger::magnitude_blur: the whole block (with the logit
    dropout and 1x1 map) and the magnitude + blur alone (with errors against float64)."""
    act = torch.bfloat16 if dev.type == "cuda" and precision == "bf16" else torch.float32
    gen = torch.Generator().manual_seed(1)
    x = torch.randn(1, h, w, dim, generator=gen).to(dev, act).requires_grad_()  # the network's layout
    g_blur = torch.randn(h, w, dim + 1, generator=gen).to(dev)
    g_mag = torch.randn(h, w, generator=gen).to(dev)
    g_logit = torch.randn(h, w, generator=gen).to(dev)
    weight = torch.randn(1, dim + 1, generator=gen).to(dev).requires_grad_()
    bias = torch.zeros(1, device=dev).requires_grad_()
    p = 0.2

    def composed_block() -> None:
        hr = x.permute(0, 3, 1, 2).float().contiguous()
        mag = hr.norm(dim=1, keepdim=True)
        blurred = gaussian_blur(torch.cat([mag, hr], dim=1), 5, 1.0, padding="reflect")
        logit = F.conv2d(F.dropout(blurred, p, training=True), weight.view(1, -1, 1, 1), bias)
        torch.autograd.backward([blurred[0].permute(1, 2, 0).contiguous(), mag[0, 0], logit[0, 0]],
                                [g_blur, g_mag, g_logit])

    def fused_block() -> None:
        blurred, mag = magnitude_blur(x[0])
        keep = blurred.new_empty(dim + 1, h, w).bernoulli_(1 - p).div_(1 - p)
        logit = masked_logit(blurred, keep, weight.view(-1), bias)
        torch.autograd.backward([blurred, mag, logit], [g_blur, g_mag, g_logit])

    def composed_op() -> None:
        torch.autograd.backward(list(_blur_composition(x)), [g_blur, g_mag])

    def fused_op() -> None:
        torch.autograd.backward(list(magnitude_blur(x[0])), [g_blur, g_mag])

    x64 = x.detach().double().requires_grad_()
    ref = _blur_composition(x64)
    ref_grad, = torch.autograd.grad(ref, x64, [g_blur.double(), g_mag.double()])

    def errs(fn) -> dict:
        out = fn()
        grad, = torch.autograd.grad(out, x, [g_blur, g_mag])
        return {"err blurred": rel_err(out[0], ref[0]), "err magnitude": rel_err(out[1], ref[1]),
                "err grad": rel_err(grad, ref_grad)}

    es = x.element_size()
    # the op's HBM traffic: x read twice (magnitude, blur) and once in the backward, blurred
    # written and its gradient read, the magnitude and its scratch, grad x written
    nbytes = h * w * (4 * dim * es + 2 * (dim + 1) * 4 + 5 * 4)
    rows = []
    for name, fn, out in (("magnitude + blur, composition", composed_op, lambda: _blur_composition(x)),
                          ("magnitude + blur, magnitude_blur", fused_op, lambda: magnitude_blur(x[0]))):
        row = {"what": name, "ms": timer(fn)}
        if fn is fused_op and dev.type == "cuda":
            row["GB/s"] = nbytes / row["ms"] / 1e6
            row["floor ms"] = nbytes / (H100_HBM_TBPS * 1e12) * 1e3
        row.update(errs(out))
        rows.append(row)
    rows += [{"what": "block, channels-first composition", "ms": timer(composed_block)},
             {"what": "block, magnitude_blur + masked_logit", "ms": timer(fused_block)}]
    return rows


def attention_rows(h: int, w: int, dim: int, dev: torch.device, timer, jitters: int = 10,
                   patch: int = 16, kernel: int = 29) -> list[dict]:
    """tiger::jittered_window_attention as the fit calls it: ``jitters`` copies of the blurred
    [h, w, dim + 1] map (FeatUp's jitters: reflect pad, zoom up to 1.8, flips) onto the
    backbone's (h / patch) x (w / patch) cells; forward, and forward + backward of <out, g>."""
    from tiger.language.featup import sample_jitter
    from tiger.language.featup_fit import jitter_coords, jitter_params, reflect_coords, window_geometry
    from tiger.ops.featup import jittered_window_attention

    gen = torch.Generator().manual_seed(2)
    size = (h // patch, w // patch)
    k, sh, sw, _, _ = window_geometry(h, w, size, kernel)
    max_pad = min(int(round(16 * min(h, w) / 224)), min(h, w) - 1)
    params = jitter_params([sample_jitter(h, w, max_pad, 1.8, True, gen) for _ in range(jitters)], h, w, "cpu")
    sy, sx = jitter_coords(params.double(), h, w)
    coords = reflect_coords(sy, h), reflect_coords(sx, w)
    features = torch.randn(h, w, dim + 1, generator=gen, dtype=torch.float64)
    logit_map = torch.randn(h, w, generator=gen, dtype=torch.float64)
    wk = 1 + 0.01 * torch.randn(k, k, generator=gen, dtype=torch.float64)
    bk = 0.01 * torch.randn(k, k, generator=gen, dtype=torch.float64)
    mask = (torch.rand(jitters, *size, generator=gen) > 0.2).double()
    g = torch.randn(jitters, *size, dim + 1, generator=gen, dtype=torch.float64)

    def inputs(dtype, device):
        return [t.to(device, dtype) for t in (features, logit_map, *coords, wk, bk, mask)]

    args = inputs(torch.float32, dev)
    leaves = [args[0].requires_grad_(), args[1].requires_grad_()]
    g32 = g.to(dev, torch.float32)

    def forward() -> None:
        with torch.no_grad():
            jittered_window_attention(*[a.detach() for a in args], (sh, sw))

    def both() -> None:
        out, _ = jittered_window_attention(*args, (sh, sw))
        torch.autograd.grad(out, leaves, g32)

    ref_args = inputs(torch.float64, "cpu")
    ref_leaves = [ref_args[0].requires_grad_(), ref_args[1].requires_grad_()]
    ref_out, _ = jittered_window_attention(*ref_args, (sh, sw))
    ref_grads = torch.autograd.grad(ref_out, ref_leaves, g)
    out, _ = jittered_window_attention(*args, (sh, sw))
    grads = torch.autograd.grad(out, leaves, g32)
    errs = {"err out": rel_err(out, ref_out), "err grad features": rel_err(grads[0], ref_grads[0]),
            "err grad logit": rel_err(grads[1], ref_grads[1])}
    what = f"{jitters} copies, {size[0]} x {size[1]} cells, kernel {k}"
    return [{"what": f"{what}, forward", "ms": timer(forward), **errs},
            {"what": f"{what}, forward + backward", "ms": timer(both)}]


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
    ap.add_argument("--only", choices=("network", "blur", "attention"), default=None,
                    help="time only the network tables, the magnitude + blur block or the attention op")
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
    if args.only in (None, "network"):
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
    if args.only in (None, "attention"):
        print_table(attention_rows(h, w, args.dim, dev, timer),
                    "jittered_window_attention at the fit's geometry (float32); error against float64")
    if args.only in (None, "blur"):
        print_table(blur_rows(args.dim, h, w, args.precision, dev, timer),
                    f"network output ({'bf16' if cuda and args.precision == 'bf16' else 'fp32'}, channels last) to "
                    "the attention op's inputs, forward + backward; errors against the float64 composition")


if __name__ == "__main__":
    main()
