"""FeatUp's implicit network per fit step, forward + backward: the fused network
(``tiger::fourier_layer_norm``: Fourier features, LayerNorm, channel dropout in one op;
``tiger::relu_scale_layer_norm``: the hidden ReLU, dropout and LayerNorm in another) against the
PyTorch composition, eager and replayed from a CUDA graph (as the fast fit runs its step), with
each one's error against the float64 composition; and each fused op alone against the
composition it replaces, with the HBM bandwidth its bytes reach. Then the step's block between
the network and the attention op (``tiger.language.featup_fit.pre_attention``: magnitude, 5-tap
reflect blur, the attention's input dropout and logit, the channels-last map the attention op
reads) in both ``ImplicitConfig.step_layout`` values, forward + backward, eager and replayed
from a CUDA graph, with errors against float64; and its two custom ops alone
(``tiger::magnitude_blur``, ``tiger::masked_logit``) against the compositions they replace.
Then ``tiger::jittered_window_attention`` at the fit's geometry (10 jittered copies, kernel 29),
every CUDA kernel variant side by side: forward, forward + backward (eager and graphed), the
backward alone, errors against float64, the backward's feature bytes and global atomics.

    python -m benchmarks.featup_ops                          # CPU, 64 x 112 pixels
    python -m benchmarks.featup_ops --device cuda            # the fit's 256 x 448, bf16 autocast
    python -m benchmarks.featup_ops --device cuda --compile  # also torch.compile'd networks
    python -m benchmarks.featup_ops --device cuda --only pre_attention  # the two step layouts
    python -m benchmarks.featup_ops --device cuda --only attention      # the attention op, every variant
    python -m benchmarks.featup_ops --device cuda --only attention --variants baseline pixel_dots
"""
from __future__ import annotations

import argparse
import contextlib
import copy

import torch

from benchmarks.common import cpu_time_ms, cuda_time_ms, print_table, rel_err
from tiger.language.featup import AttentionDownsampler, ImplicitNet, _min_max
from tiger.language.featup_fit import BLUR_RADIUS, BLUR_SIGMA, pre_attention
from tiger.ops.featup import WINDOW_VARIANTS, fourier_layer_norm, magnitude_blur, masked_logit, relu_scale_layer_norm
from tiger.testing.cuda_graphs import capture
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
    with torch.cuda.device(device):
        graph, _ = capture(step, warmup=3)
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


LAYOUTS = ("channels_first", "channels_last")


def _pre_attention_grads(hr: torch.Tensor, down: AttentionDownsampler, layout: str, grads: list[torch.Tensor],
                         blur_pin: float = 0.1) -> tuple:
    """``pre_attention`` of the channels-last network output ``hr`` [1, h, w, C] and its backward
    for the incoming gradients of (attention features, logit map, magnitude) and the fit's blur
    pin term; returns (features, logit map, grad hr, grad of the logit's weight)."""
    lin = down.attention[1]
    pre = pre_attention(hr.permute(0, 3, 1, 2), down, layout)
    g_features, g_logit, g_mag = grads
    pin = blur_pin * (pre.hr_blurred() - pre.hr).square().mean()
    grad_hr, grad_w = torch.autograd.grad([pre.features, pre.logit_map, pre.hr_mag, pin], [hr, lin.weight],
                                          [g_features, g_logit, g_mag.view(pre.hr_mag.shape), torch.ones_like(pin)])
    return pre.features, pre.logit_map, grad_hr, grad_w


def pre_attention_rows(dim: int, h: int, w: int, precision: str, dev: torch.device, timer,
                       dropout: float = 0.2) -> list[dict]:
    """The fit step's block from the network's output (channels last, bf16 on CUDA as under the
    fit's autocast) to the attention op's inputs, in both step layouts, forward + backward with
    the dropout on; errors (dropout off) against the float64 channels-first composition."""
    act = torch.bfloat16 if dev.type == "cuda" and precision == "bf16" else torch.float32
    gen = torch.Generator().manual_seed(1)
    hr = torch.randn(1, h, w, dim, generator=gen).to(dev, act).requires_grad_()  # the network's layout
    grads = [torch.randn(h, w, dim + 1, generator=gen).to(dev), torch.randn(h, w, generator=gen).to(dev),
             torch.randn(h, w, generator=gen).to(dev)]
    torch.manual_seed(0)
    down = AttentionDownsampler(dim + 1, 29, gen, dropout).to(dev).train()
    still = copy.deepcopy(down)
    still.dropout = 0.0
    ref_down = copy.deepcopy(still).double()
    hr64 = hr.detach().double().requires_grad_()
    ref = _pre_attention_grads(hr64, ref_down, "channels_first", [g.double() for g in grads])
    rows = []
    for layout in LAYOUTS:
        def step(layout=layout) -> None:
            _pre_attention_grads(hr, down, layout, grads)

        row = {"what": f"pre-attention block, {layout}", "eager ms": timer(step)}
        if dev.type == "cuda":
            row["graph ms"] = timer(graphed(step, dev))
        out = _pre_attention_grads(hr, still, layout, grads)
        row.update({f"err {name}": rel_err(a, b)
                    for name, a, b in zip(("features", "logit", "grad hr", "grad w"), out, ref)})
        rows.append(row)
    return rows


def pre_attention_op_rows(dim: int, h: int, w: int, precision: str, dev: torch.device, timer,
                          dropout: float = 0.2) -> list[dict]:
    """tiger::magnitude_blur and tiger::masked_logit alone against the compositions they replace
    (from the network's channels-last output / the blurred map), forward + backward."""
    act = torch.bfloat16 if dev.type == "cuda" and precision == "bf16" else torch.float32
    gen = torch.Generator().manual_seed(2)
    u = dim + 1
    hr = torch.randn(1, h, w, dim, generator=gen).to(dev, act).requires_grad_()
    g_blur, g_mag = torch.randn(h, w, u, generator=gen).to(dev), torch.randn(h, w, generator=gen).to(dev)
    blurred = torch.randn(h, w, u, generator=gen).to(dev).requires_grad_()
    blurred_cf = blurred.detach().permute(2, 0, 1)[None].contiguous().requires_grad_()
    weight = torch.randn(u, generator=gen).to(dev).requires_grad_()
    bias = torch.zeros(1, device=dev).requires_grad_()
    g_logit = torch.randn(h, w, generator=gen).to(dev)

    def blur_composed() -> None:
        x = hr.permute(0, 3, 1, 2).float().contiguous()
        mag = x.norm(dim=1, keepdim=True)
        out = gaussian_blur(torch.cat([mag, x], dim=1), 2 * BLUR_RADIUS + 1, BLUR_SIGMA, padding="reflect")
        torch.autograd.grad([out[0].permute(1, 2, 0).contiguous(), mag[0, 0]], hr, [g_blur, g_mag])

    def blur_fused() -> None:
        torch.autograd.grad(list(magnitude_blur(hr[0], BLUR_RADIUS, BLUR_SIGMA)), hr, [g_blur, g_mag])

    def logit_composed() -> None:
        out = torch.nn.functional.conv2d(torch.nn.functional.dropout(blurred_cf, dropout, training=True),
                                         weight.view(1, -1, 1, 1), bias)
        torch.autograd.grad(out[0, 0], [blurred_cf, weight, bias], g_logit)

    def logit_fused() -> None:
        keep = torch.empty(u, h, w, dtype=torch.bool, device=dev).bernoulli_(1 - dropout)
        torch.autograd.grad(masked_logit(blurred, weight, bias, keep, 1 / (1 - dropout)), [blurred, weight, bias],
                            g_logit)

    es = hr.element_size()
    # magnitude_blur's HBM traffic: x read twice (magnitude, blur) and once in the backward, the
    # blurred map written and its gradient read, the magnitude and the backward's scale, grad x
    blur_bytes = h * w * (4 * dim * es + 2 * u * 4 + 5 * 4)
    # masked_logit's: the map read twice and its gradient written, the 1-byte keep mask drawn and
    # read twice, the logit written and its gradient read
    logit_bytes = h * w * (3 * u * 4 + 3 * u + 2 * 4)
    return (_timed_pair("magnitude + blur (magnitude_blur)", blur_composed, blur_fused, blur_bytes, dev, timer)
            + _timed_pair("dropout + logit (masked_logit)", logit_composed, logit_fused, logit_bytes, dev, timer))


def _tile_extents(coord_y: torch.Tensor, coord_x: torch.Tensor, size: tuple[int, int], k: int, sh: int, sw: int,
                  h: int, w: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """First row [J, FH], rows [J, FH], first column [J, FW] and columns [J, FW] of each cell's
    source tile (the CUDA kernels' r0, tr, c0, tc): the span of the window's bilinear taps, as
    ``axis_tap`` clamps them."""
    def span(coords: torch.Tensor, cells: int, stride: int, n: int) -> tuple[torch.Tensor, torch.Tensor]:
        c = coords.double().clamp(0, n - 1)
        idx = c.floor()
        hi = torch.where(idx + 1 < n, idx + 1, idx)
        win = torch.arange(k) + stride * torch.arange(cells).view(-1, 1)  # [cells, k]
        lo = idx[:, win].amin(-1)
        return lo.long(), (hi[:, win].amax(-1) - lo + 1).long()

    return (*span(coord_y, size[0], sh, h), *span(coord_x, size[1], sw, w))


def attention_traffic(coords: tuple[torch.Tensor, torch.Tensor], size: tuple[int, int], k: int, sh: int, sw: int,
                      h: int, w: int, channels: int, group: int = 4) -> dict:
    """Feature bytes read and global atomics per variant (estimates from the geometry, float32):
    the forward's reads (each cell's tile; staged_tiles and after: the union of the tiles of
    ``group`` neighbouring cells of a window row, from a bfloat16 copy for staged_tiles_bf16), the
    backward's dots' reads (each cell's tile, from L2 or HBM; pixel_dots and after: every feature
    once, float32, rounded to bfloat16 on the way for staged_tiles_bf16), and
    the backward's global atomics on the logit map's gradient (baseline: the taps of the K*K window
    pixels; shared_scatter and after: at most one per tile pixel)."""
    cy, cx = coords
    _, rows, c0, cols = _tile_extents(cy, cx, size, k, sh, sw, h, w)
    tile_px = int((rows.unsqueeze(2) * cols.unsqueeze(1)).sum())  # sum over cells of tr * tc
    union = torch.zeros(cols.shape[0], dtype=torch.long)  # per jitter: the groups' column unions
    for g0 in range(0, size[1], group):
        lo, hi = c0[:, g0:g0 + group], c0[:, g0:g0 + group] + cols[:, g0:g0 + group]
        union += hi.amax(-1) - lo.amin(-1)
    grouped_px = int((rows.sum(-1) * union).sum())
    ty_second = (cy.double().clamp(0, h - 1).floor() + 1 < h).double()
    tx_second = (cx.double().clamp(0, w - 1).floor() + 1 < w).double()
    win_y = torch.arange(k) + sh * torch.arange(size[0]).view(-1, 1)
    win_x = torch.arange(k) + sw * torch.arange(size[1]).view(-1, 1)
    taps_y = (1 + ty_second[:, win_y]).sum(-1)  # [J, FH]: taps of the window's rows
    taps_x = (1 + tx_second[:, win_x]).sum(-1)
    window_atomics = int((taps_y.unsqueeze(2) * taps_x.unsqueeze(1)).sum())
    per_cell, once, grouped = tile_px * channels * 4, h * w * channels * 4, grouped_px * channels * 4
    return {"tile_px": tile_px,
            "forward_bytes": {"baseline": per_cell, "shared_scatter": per_cell, "pixel_dots": per_cell,
                              "staged_tiles": grouped, "staged_tiles_bf16": grouped // 2},
            "dots_bytes": {"baseline": per_cell, "shared_scatter": per_cell, "pixel_dots": once,
                           "staged_tiles": once, "staged_tiles_bf16": once},
            "atomics": {"baseline": window_atomics, "shared_scatter": tile_px, "pixel_dots": tile_px,
                        "staged_tiles": tile_px, "staged_tiles_bf16": tile_px}}


def attention_rows(h: int, w: int, dim: int, dev: torch.device, timer, jitters: int = 10,
                   patch: int = 16, kernel: int = 29, variants: tuple[str, ...] | None = None) -> list[dict]:
    """tiger::jittered_window_attention as the fit calls it: ``jitters`` copies of the blurred
    [h, w, dim + 1] map (FeatUp's jitters: reflect pad, zoom up to 1.8, flips) onto the
    backbone's (h / patch) x (w / patch) cells; per kernel variant (CUDA; the CPU runs the
    reference kernels only): forward, forward + backward (eager and, on CUDA, replayed from a
    CUDA graph as the fit runs it), the backward alone, each one's errors against the float64 CPU
    op, and the feature bytes read by the forward and by the backward's dots and the backward's
    global atomics (estimates from the geometry, :func:`attention_traffic`)."""
    from tiger.language.featup import sample_jitter
    from tiger.language.featup_fit import jitter_coords, jitter_params, reflect_coords, window_geometry
    from tiger.ops.featup import WINDOW_VARIANTS, jittered_window_attention

    gen = torch.Generator().manual_seed(3)
    size = (h // patch, w // patch)
    k, sh, sw, _, _ = window_geometry(h, w, size, kernel)
    max_pad = min(int(round(30 * min(h, w) / 224)), min(h, w) - 1)  # ImplicitConfig.max_pad, scaled
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

    ref_args = inputs(torch.float64, "cpu")
    ref_leaves = [ref_args[0].requires_grad_(), ref_args[1].requires_grad_(), ref_args[4].requires_grad_(),
                  ref_args[5].requires_grad_()]
    ref_out, _ = jittered_window_attention(*ref_args, (sh, sw))
    ref_grads = torch.autograd.grad(ref_out, ref_leaves, g)
    traffic = attention_traffic(coords, size, k, sh, sw, h, w, dim + 1)
    g32 = g.to(dev, torch.float32)
    what = f"{jitters} copies, {size[0]} x {size[1]} cells, kernel {k}"
    rows = []
    for variant in variants or (WINDOW_VARIANTS if dev.type == "cuda" else ("baseline",)):
        args = inputs(torch.float32, dev)
        leaves = [args[0].requires_grad_(), args[1].requires_grad_(), args[4].requires_grad_(),
                  args[5].requires_grad_()]

        def forward(variant=variant, args=args) -> None:
            with torch.no_grad():
                jittered_window_attention(*[a.detach() for a in args], (sh, sw), variant)

        def both(variant=variant, args=args, leaves=leaves) -> None:
            out, _ = jittered_window_attention(*args, (sh, sw), variant)
            torch.autograd.grad(out, leaves, g32)

        row = {"what": f"{what}, {variant}", "fwd ms": timer(forward), "fwd+bwd ms": timer(both)}
        if dev.type == "cuda":  # needs a non-default current stream: see main()
            row["fwd+bwd graph ms"] = timer(graphed(both, dev))
        out, _ = jittered_window_attention(*args, (sh, sw), variant)
        grads = torch.autograd.grad(out, leaves, g32, retain_graph=True)

        def backward(out=out, leaves=leaves) -> None:
            torch.autograd.grad(out, leaves, g32, retain_graph=True)

        row["bwd ms"] = timer(backward)
        row.update({"err out": rel_err(out, ref_out)})
        row.update({f"err grad {name}": rel_err(a, r)
                    for name, a, r in zip(("features", "logit", "w", "b"), grads, ref_grads)})
        row["fwd F GB"] = traffic["forward_bytes"][variant] / 1e9
        row["bwd dots F GB"] = traffic["dots_bytes"][variant] / 1e9
        row["bwd atomics M"] = traffic["atomics"][variant] / 1e6
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
    ap.add_argument("--only", choices=("network", "pre_attention", "attention"), default=None,
                    help="time only the network tables, the pre-attention block (both step layouts) or the "
                         "attention op")
    ap.add_argument("--variants", nargs="+", default=None, choices=WINDOW_VARIANTS,
                    help="jittered_window_attention kernel variants to time side by side (default: all on CUDA, "
                         "the reference kernels on the CPU)")
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
    act = "bf16" if cuda and args.precision == "bf16" else "fp32"
    if args.only in (None, "pre_attention"):
        print_table(pre_attention_rows(args.dim, h, w, args.precision, dev, timer),
                    f"network output ({act}, channels last) to the attention op's inputs, per step layout, "
                    "forward + backward (dropout 0.2); errors (dropout off) against the float64 channels-first block")
        print_table(pre_attention_op_rows(args.dim, h, w, args.precision, dev, timer),
                    "the channels-last block's ops alone against the compositions they replace, forward + backward")
    if args.only in (None, "attention"):
        # on a side stream: the rows' leaves and autograd nodes then never sit on the legacy default
        # stream, on which a graph capture may not depend (on the default stream the first capture
        # failed on an H100: 'operation would make the legacy stream depend on a capturing blocking
        # stream'; torch warns of AccumulateGrad nodes on the default stream)
        side = torch.cuda.Stream(dev) if dev.type == "cuda" else None
        with torch.cuda.stream(side) if side is not None else contextlib.nullcontext():
            rows = attention_rows(h, w, args.dim, dev, timer, variants=args.variants)
        print_table(rows,
                    "jittered_window_attention at the fit's geometry (float32) per kernel variant; errors against "
                    "the float64 CPU op; feature bytes read by the forward and the backward's dots, global atomics "
                    "(estimates)")


if __name__ == "__main__":
    main()
