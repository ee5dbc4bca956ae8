"""The implicit network's fused ops against the PyTorch composition they replace, in float64 on
the CPU, values and gradients: ``tiger::fourier_layer_norm`` (csrc/featup/fourier*: Fourier
features, LayerNorm, the channel dropout's multiplier) and ``tiger::relu_scale_layer_norm``
(csrc/featup/relu_norm*: ReLU, the dropout's multiplier, LayerNorm); the fused network and the
fast fit with it against the composition; and the CUDA kernels against the CPU kernels."""
import dataclasses

import pytest
import torch
import torch.nn.functional as F

import tiger.ops
from tiger.language.featup import FourierFeaturizer, ImplicitConfig, ImplicitNet, ImplicitUpsampler
from tiger.ops.featup import fourier_layer_norm, relu_scale_layer_norm
from tiger.testing.cuda_graphs import capture

CUDA = torch.cuda.is_available() and tiger.ops.cuda_enabled()
needs_cuda = pytest.mark.skipif(not CUDA, reason="needs CUDA")
F64 = torch.float64


def op_args(b=2, h=5, w=7, n_freqs=4, seed=0, dtype=F64, device="cpu", scale=True):
    """Per-pixel inputs [B, N, 5] (min-max scaled like the network's), freqs, phase, LayerNorm
    weight/bias and a dropout-like scale [B, C], all from one seed."""
    gen = torch.Generator().manual_seed(seed)
    image = torch.rand(b, 3, h, w, generator=gen, dtype=dtype) - 0.5
    inputs = FourierFeaturizer.pixel_inputs(image).reshape(b, h * w, 5)
    fourier = FourierFeaturizer(n_freqs, gen).to(dtype)
    c = fourier.out_dim
    weight = 1 + 0.3 * torch.randn(c, generator=gen, dtype=dtype)
    bias = 0.2 * torch.randn(c, generator=gen, dtype=dtype)
    s = (torch.rand(b, c, generator=gen) > 0.2).to(dtype) / 0.8 if scale else None
    args = [inputs, fourier.frequencies("cpu", dtype), fourier.biases.detach().clone(), weight, bias, s]
    return [t.to(device) if t is not None else None for t in args], image, fourier


def reference(inputs, freqs, phase, weight, bias, scale, eps=1e-5):
    """The composition: FourierFeaturizer.pixels' formula, F.layer_norm, times the scale."""
    b, n, _ = inputs.shape
    nf = freqs.shape[0]
    feats = inputs.unsqueeze(-2) * freqs.view(nf, 1)  # [B, N, F, 5]
    x = torch.cat([torch.sin(feats + phase[0].reshape(nf, 5)).reshape(b, n, -1),
                   torch.cos(feats + phase[1].reshape(nf, 5)).reshape(b, n, -1), inputs[..., 2:]], -1)
    y = F.layer_norm(x, x.shape[-1:], weight, bias, eps)
    return y * scale.unsqueeze(1) if scale is not None else y


def test_reference_is_the_featurizers_pixels():
    (inputs, freqs, phase, weight, bias, _), image, fourier = op_args(scale=False)
    ones, zeros = torch.ones_like(weight), torch.zeros_like(bias)
    expected = F.layer_norm(fourier.pixels(image), weight.shape, ones, zeros)
    torch.testing.assert_close(reference(inputs, freqs, fourier.biases, ones, zeros, None).view(expected.shape),
                               expected)


@pytest.mark.parametrize("scale", [True, False])
@pytest.mark.parametrize("n_freqs,hw", [(4, (5, 7)), (30, (9, 11)), (1, (1, 3))])
def test_op_equals_the_composition_in_float64(scale, n_freqs, hw):
    args, _, _ = op_args(h=hw[0], w=hw[1], n_freqs=n_freqs, scale=scale)
    inputs, freqs, phase, weight, bias, s = args
    leaves = [t.clone().requires_grad_() for t in (inputs, phase, weight, bias)]
    ref = reference(leaves[0], freqs, leaves[1], leaves[2], leaves[3], s)
    out = fourier_layer_norm(leaves[0], freqs, leaves[1], leaves[2], leaves[3], s)
    assert out.shape == (2, hw[0] * hw[1], 10 * n_freqs + 3) and out.dtype == F64
    torch.testing.assert_close(out, ref, atol=1e-12, rtol=1e-12)
    g = torch.randn(ref.shape, generator=torch.Generator().manual_seed(3), dtype=F64)
    ref_grads = torch.autograd.grad((ref * g).sum(), leaves)
    grads = torch.autograd.grad((out * g).sum(), leaves)
    for name, a, b in zip(("inputs", "phase", "weight", "bias"), grads, ref_grads):
        torch.testing.assert_close(a, b, atol=1e-10, rtol=1e-10, msg=lambda m, n=name: f"grad {n}: {m}")


def test_float32_and_bf16_output_follow_the_float64_reference():
    args, _, _ = op_args(h=16, w=24, n_freqs=30)
    ref = reference(*args)
    args32 = [t.float() if t is not None else None for t in args]
    out32 = fourier_layer_norm(*args32)
    # the float32 composition rounds the phases as the op does (product, then sum)...
    torch.testing.assert_close(out32, reference(*args32), atol=2e-5, rtol=1e-5)
    # ...and both differ from float64 there: phases reach ~1e4 radians, where a float32 ulp is ~1e-3
    assert (out32.double() - ref).abs().max() < 1e-2
    bf = fourier_layer_norm(*args32, out_dtype=torch.bfloat16)
    assert bf.dtype == torch.bfloat16
    torch.testing.assert_close(bf.float(), out32, atol=3e-2, rtol=1e-2)


def test_gradcheck_and_opcheck():
    args, _, _ = op_args(b=2, h=3, w=4, n_freqs=2)
    inputs, _, phase, weight, bias, s = args
    # moderate frequencies: at FeatUp's top one (e^10) finite differences of the inputs cannot resolve sin
    freqs = torch.tensor([0.7, 3.0], dtype=F64)
    leaves = [t.clone().requires_grad_() for t in (inputs, phase, weight, bias)]
    fn = lambda i, p, w, b: fourier_layer_norm(i, freqs, p, w, b, s)  # noqa: E731
    assert torch.autograd.gradcheck(fn, tuple(leaves))
    assert torch.autograd.gradcheck(lambda i, p, w, b: fourier_layer_norm(i, freqs, p, w, b, None), tuple(leaves))
    op = torch.ops.tiger.fourier_layer_norm
    torch.library.opcheck(op, (inputs, freqs, phase, weight, bias, s, 1e-5, None))
    torch.library.opcheck(op, (*leaves[:1], freqs, *leaves[1:], s, 1e-5, None))
    torch.library.opcheck(op, (inputs.float(), freqs.float(), *(t.float().requires_grad_() for t in leaves[1:]),
                               None, 1e-5, torch.bfloat16))


def test_backward_sums_do_not_depend_on_the_thread_count():
    args, _, _ = op_args(b=1, h=40, w=60, n_freqs=6, dtype=torch.float32)
    inputs, freqs, phase, weight, bias, s = args
    leaves = [t.clone().requires_grad_() for t in (phase, weight, bias)]
    g = torch.randn(1, 2400, 63, generator=torch.Generator().manual_seed(1))

    def grads():
        out = fourier_layer_norm(inputs, freqs, *leaves, s)
        return torch.autograd.grad((out * g).sum(), leaves)

    threads = torch.get_num_threads()
    try:
        torch.set_num_threads(1)
        one = grads()
        torch.set_num_threads(2)
        two = grads()
    finally:
        torch.set_num_threads(threads)
    for a, b in zip(one, two):
        assert torch.equal(a, b)


def test_bad_inputs_name_the_tensor():
    (inputs, freqs, phase, weight, bias, s), _, _ = op_args()
    with pytest.raises(RuntimeError, match="inputs must be \\[B, N, 5\\]"):
        fourier_layer_norm(inputs[..., :4], freqs, phase, weight, bias, s)
    with pytest.raises(RuntimeError, match="phase must have shape"):
        fourier_layer_norm(inputs, freqs, phase[:, :, :2], weight, bias, s)
    with pytest.raises(RuntimeError, match="weight must have shape"):
        fourier_layer_norm(inputs, freqs, phase, weight[1:], bias, s)
    with pytest.raises(RuntimeError, match="scale must have shape"):
        fourier_layer_norm(inputs, freqs, phase, weight, bias, s[:1])
    with pytest.raises(RuntimeError, match="bias \\(Float\\) must have the dtype of inputs"):
        fourier_layer_norm(inputs, freqs, phase, weight, bias.float(), s)
    with pytest.raises(RuntimeError, match="out_dtype must be"):
        fourier_layer_norm(inputs, freqs, phase, weight, bias, s, out_dtype=torch.float32)
    with pytest.raises(ValueError, match="freqs and scale are not differentiable"):
        fourier_layer_norm(inputs, freqs.clone().requires_grad_(), phase, weight, bias, s)


# ----------------------------------------------------------------------------- relu_scale_layer_norm
def norm_args(b=2, n=35, d=12, seed=0, dtype=F64, device="cpu", scale=True):
    gen = torch.Generator().manual_seed(seed)
    x = torch.randn(b, n, d, generator=gen, dtype=F64)
    x[0, 0, :3] = 0.0  # ReLU's kink: no gradient there (as torch.relu)
    pdt = F64 if dtype == F64 else torch.float32
    weight = (1 + 0.3 * torch.randn(d, generator=gen, dtype=F64)).to(pdt)
    bias = (0.2 * torch.randn(d, generator=gen, dtype=F64)).to(pdt)
    s = ((torch.rand(b, d, generator=gen) > 0.2).to(F64) / 0.8).to(pdt) if scale else None
    return [t.to(device) if t is not None else None for t in (x.to(dtype), weight, bias, s)]


def norm_reference(x, weight, bias, scale, eps=1e-5):
    z = torch.relu(x)
    z = z * scale.unsqueeze(1) if scale is not None else z
    return F.layer_norm(z, z.shape[-1:], weight, bias, eps)


@pytest.mark.parametrize("scale", [True, False])
@pytest.mark.parametrize("d", [1, 12, 128, 300])
def test_relu_norm_equals_the_composition_in_float64(scale, d):
    x, weight, bias, s = norm_args(d=d, scale=scale)
    leaves = [t.clone().requires_grad_() for t in (x, weight, bias)]
    ref = norm_reference(*leaves, s)
    out = relu_scale_layer_norm(*leaves, s)
    torch.testing.assert_close(out, ref, atol=1e-12, rtol=1e-12)
    g = torch.randn(ref.shape, generator=torch.Generator().manual_seed(3), dtype=F64)
    for name, a, b in zip(("x", "weight", "bias"), torch.autograd.grad((out * g).sum(), leaves),
                          torch.autograd.grad((ref * g).sum(), leaves)):
        torch.testing.assert_close(a, b, atol=1e-10, rtol=1e-10, msg=lambda m, n=name: f"grad {n}: {m}")


def test_relu_norm_bf16_follows_the_float32_composition():
    x, weight, bias, s = norm_args(n=64, d=128, dtype=torch.bfloat16)
    out = relu_scale_layer_norm(x, weight, bias, s)
    assert out.dtype == torch.bfloat16
    torch.testing.assert_close(out.float(), norm_reference(x.float(), weight, bias, s), atol=3e-2, rtol=1e-2)


def test_relu_norm_gradcheck_and_opcheck():
    x, weight, bias, s = norm_args(b=2, n=5, d=6)
    x = torch.where(x >= 0, x + 0.05, x - 0.05)  # away from the kink for finite differences
    leaves = [t.clone().requires_grad_() for t in (x, weight, bias)]
    assert torch.autograd.gradcheck(lambda *a: relu_scale_layer_norm(*a, s), tuple(leaves))
    assert torch.autograd.gradcheck(lambda *a: relu_scale_layer_norm(*a, None), tuple(leaves))
    op = torch.ops.tiger.relu_scale_layer_norm
    torch.library.opcheck(op, (x, s, weight, bias, 1e-5))
    torch.library.opcheck(op, (leaves[0], s, *leaves[1:], 1e-5))
    xb, wb, bb, sb = norm_args(b=1, n=7, d=9, dtype=torch.bfloat16)
    torch.library.opcheck(op, (xb.requires_grad_(), None, wb.requires_grad_(), bb, 1e-5))


def test_relu_norm_bad_inputs_name_the_tensor():
    x, weight, bias, s = norm_args()
    with pytest.raises(RuntimeError, match="x must be \\[B, N, D\\]"):
        relu_scale_layer_norm(x[0], weight, bias, s)
    with pytest.raises(RuntimeError, match="weight must have shape"):
        relu_scale_layer_norm(x, weight[1:], bias, s)
    with pytest.raises(RuntimeError, match="scale must be Double"):
        relu_scale_layer_norm(x, weight, bias, s.float())
    with pytest.raises(ValueError, match="scale is not differentiable"):
        relu_scale_layer_norm(x, weight, bias, s.clone().requires_grad_())


# ----------------------------------------------------------------------------- the network and the fit
def _net_pair(n_freqs=5, out_dim=6, seed=0, dtype=F64):
    fused = ImplicitNet(out_dim, n_freqs, torch.Generator().manual_seed(seed)).to(dtype)
    with torch.no_grad():  # non-trivial LayerNorm affines
        gen = torch.Generator().manual_seed(seed + 1)
        for m in (fused.net[0].norm, fused.net[5].norm):
            m.weight.add_(0.3 * torch.randn(m.weight.shape, generator=gen, dtype=dtype))
            m.bias.add_(0.2 * torch.randn(m.bias.shape, generator=gen, dtype=dtype))
    composed = ImplicitNet(out_dim, n_freqs, fused=False).to(dtype)
    composed.load_state_dict(fused.state_dict())
    return fused, composed


@pytest.mark.parametrize("training", [False, True])
def test_fused_network_equals_the_composition(training):
    fused, composed = _net_pair()
    fused.train(training)
    composed.train(training)
    image = torch.rand(2, 3, 9, 13, generator=torch.Generator().manual_seed(5), dtype=F64)
    outs, grads = [], []
    for net in (fused, composed):
        torch.manual_seed(11)  # the same dropout masks: the fused net draws them in the same order
        out = net.forward_pixels(image)
        g = torch.randn(out.shape, generator=torch.Generator().manual_seed(6), dtype=F64)
        grads.append(torch.autograd.grad((out * g).sum(), list(net.parameters())))
        outs.append(out)
    torch.testing.assert_close(outs[0], outs[1], atol=1e-12, rtol=1e-12)
    torch.testing.assert_close(outs[1], composed(image), atol=1e-12, rtol=1e-12) if not training else None
    names = [n for n, _ in fused.named_parameters()]
    for name, a, b in zip(names, *grads):
        torch.testing.assert_close(a, b, atol=1e-10, rtol=1e-10, msg=lambda m, n=name: f"grad {n}: {m}")


def test_fast_fit_with_the_fused_network_equals_the_composition():
    """A few fast-fit steps on the CPU (float32, dropout on): the same losses and map either way."""
    img = torch.rand(3, 40, 56, generator=torch.Generator().manual_seed(0))
    backbone = lambda x: F.avg_pool2d(x.repeat(1, 4, 1, 1), 8)  # noqa: E731
    cfg = ImplicitConfig(steps=6, stop_change=0.0, n_views=12, pca_batch=12, proj_dim=8, kernel_size=7,
                         jitters_per_step=3, n_freqs=8)
    fused = ImplicitUpsampler.fit(img, backbone, cfg)
    composed = ImplicitUpsampler.fit(img, backbone, dataclasses.replace(cfg, fused_network=False))
    assert fused.net.fused and not composed.net.fused
    torch.testing.assert_close(torch.tensor(fused.history), torch.tensor(composed.history), rtol=1e-4, atol=1e-6)
    torch.testing.assert_close(fused(), composed(), rtol=1e-3, atol=1e-4)


# ----------------------------------------------------------------------------- CUDA
def _run(args, device, out_dtype=None):
    inputs, freqs, phase, weight, bias, s = [t.to(device) if t is not None else None for t in args]
    leaves = [t.clone().requires_grad_() for t in (inputs, phase, weight, bias)]
    out = fourier_layer_norm(leaves[0], freqs, *leaves[1:], s, out_dtype=out_dtype)
    g = torch.randn(out.shape, generator=torch.Generator().manual_seed(4)).to(device, out.dtype)
    grads = torch.autograd.grad((out.to(inputs.dtype) * g.to(inputs.dtype)).sum(), leaves)
    return [t.detach().cpu() for t in (out, *grads)]


@needs_cuda
@pytest.mark.parametrize("dtype,out_dtype", [(F64, None), (torch.float32, None), (torch.float32, torch.bfloat16)])
@pytest.mark.parametrize("shape", [dict(), dict(b=1, h=33, w=47, n_freqs=30), dict(b=2, h=17, w=9, n_freqs=50),
                                   dict(b=1, h=64, w=112, n_freqs=30)])
def test_cuda_equals_cpu(dtype, out_dtype, shape):
    args, _, _ = op_args(dtype=dtype, **shape)
    cpu, gpu = _run(args, "cpu", out_dtype), _run(args, "cuda", out_dtype)
    if dtype == F64:
        tol = dict(atol=1e-10, rtol=1e-10)
    elif out_dtype is None:
        tol = dict(atol=2e-4, rtol=1e-4)
    else:
        tol = dict(atol=3e-2, rtol=2e-2)  # one bf16 rounding apart at most
    for name, a, b in zip(("out", "grad inputs", "grad phase", "grad weight", "grad bias"), gpu, cpu):
        scale = max(1.0, b.abs().max().item()) if name != "out" else 1.0
        torch.testing.assert_close(a.double() / scale, b.double() / scale, **tol, msg=lambda m, n=name: f"{n}: {m}")


def _run_norm(args, device):
    x, weight, bias, s = [t.to(device) if t is not None else None for t in args]
    leaves = [t.clone().requires_grad_() for t in (x, weight, bias)]
    out = relu_scale_layer_norm(*leaves, s)
    g = torch.randn(out.shape, generator=torch.Generator().manual_seed(4)).to(device, out.dtype)
    grads = torch.autograd.grad((out * g).sum(), leaves)
    return [t.detach().cpu() for t in (out, *grads)]


@needs_cuda
@pytest.mark.parametrize("dtype", [F64, torch.float32, torch.bfloat16])
@pytest.mark.parametrize("shape", [dict(), dict(b=1, n=4000, d=128), dict(b=2, n=333, d=200), dict(b=1, n=50, d=512)])
def test_cuda_relu_norm_equals_cpu(dtype, shape):
    args = norm_args(dtype=dtype, **shape)
    cpu, gpu = _run_norm(args, "cpu"), _run_norm(args, "cuda")
    tol = {F64: dict(atol=1e-10, rtol=1e-10), torch.float32: dict(atol=2e-4, rtol=1e-4),
           torch.bfloat16: dict(atol=3e-2, rtol=2e-2)}[dtype]
    for name, a, b in zip(("out", "grad x", "grad weight", "grad bias"), gpu, cpu):
        scale = max(1.0, b.abs().max().item()) if name in ("grad weight", "grad bias") else 1.0
        torch.testing.assert_close(a.double() / scale, b.double() / scale, **tol, msg=lambda m, n=name: f"{n}: {m}")


@needs_cuda
def test_cuda_backward_is_deterministic_and_graph_capturable():
    args, _, _ = op_args(b=1, h=96, w=160, n_freqs=30, dtype=torch.float32, device="cuda")
    inputs, freqs, phase, weight, bias, s = args
    leaves = [t.clone().requires_grad_() for t in (phase, weight, bias)]
    g = torch.randn(1, 96 * 160, 303, device="cuda", dtype=torch.bfloat16)

    def grads():
        out = fourier_layer_norm(inputs, freqs, *leaves, s, out_dtype=torch.bfloat16)
        return torch.autograd.grad((out * g).sum(), leaves)

    first, second = grads(), grads()
    for a, b in zip(first, second):
        assert torch.equal(a, b)
    graph, captured = capture(grads)
    graph.replay()
    torch.cuda.synchronize()
    for a, b in zip(captured, first):
        assert torch.equal(a, b)


@needs_cuda
def test_cuda_fast_fit_fused_follows_the_composition():
    """The fast fit on CUDA (fp32, no dropout) with the fused network against the composition."""
    img = torch.rand(3, 48, 80, generator=torch.Generator().manual_seed(0)).cuda()
    backbone = lambda x: F.avg_pool2d(x.repeat(1, 4, 1, 1), 8)  # noqa: E731
    cfg = ImplicitConfig(steps=12, stop_change=0.0, n_views=16, pca_batch=16, proj_dim=8, kernel_size=11,
                         jitters_per_step=4, n_freqs=6, dropout=0.0, precision="fp32")
    fused = ImplicitUpsampler.fit(img, backbone, cfg)
    composed = ImplicitUpsampler.fit(img, backbone, dataclasses.replace(cfg, fused_network=False))
    torch.testing.assert_close(torch.tensor(fused.history), torch.tensor(composed.history), rtol=2e-3, atol=1e-5)
    cos = F.cosine_similarity(fused(), composed(), dim=0)
    assert cos.mean() >= 0.999 and cos.min() > 0.99, (cos.mean(), cos.min())
