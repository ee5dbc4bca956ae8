"""On a GPU: the fp8_rows kernels equal their CPU references (quantisation bit-exact, GEGLU
within one rounding), the FP8 linear (torch._scaled_mm, row-wise scales) equals its float32
emulation on the same quantised operands within bfloat16 output rounding, the default kernels
(fused GEGLU, 4x4 downsampling, norm-folded biases) in a graphed float32 step equal diffusers'
computation eagerly, and a graphed InstructPix2Pix step with FP8 matmuls on top equals its eager
step."""
import pytest
import torch

from tiger.edit.guidance import model_kernels as mk
from tiger.ops.fp8_rows import geglu, quantize_rows_fp8

pytestmark = [pytest.mark.cuda, pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")]


def _needs_fp8():
    ok, why = mk.fp8_supported("cuda")
    if not ok:
        pytest.skip(why)


@pytest.mark.parametrize("dtype", [torch.float32, torch.bfloat16, torch.float16])
@pytest.mark.parametrize("cols", [320, 1280, 24, 7])  # vector and scalar paths
@pytest.mark.parametrize("use_geglu", [False, True])
def test_quantize_rows_cuda_equals_cpu(dtype, cols, use_geglu):
    if use_geglu and cols % 2:
        pytest.skip("GEGLU needs an even width")
    x = (torch.randn(37, cols, generator=torch.Generator().manual_seed(0)) * 3).to(dtype)
    x[5] = 0
    q_cpu, s_cpu = quantize_rows_fp8(x, geglu=use_geglu)
    q, s = quantize_rows_fp8(x.cuda(), geglu=use_geglu)
    same = q.cpu().view(torch.uint8) == q_cpu.view(torch.uint8)
    if use_geglu:  # CUDA's erff and the CPU's erf may differ in the last float bit: so may a row's
        # amax (its scale, by a float ulp: seen on the H100) and, rarely, a code at a rounding tie
        assert torch.allclose(s.cpu(), s_cpu, rtol=4 * torch.finfo(torch.float32).eps, atol=0)
        assert float(same.float().mean()) > 0.999
        assert float((q.cpu().float() - q_cpu.float()).abs().max()) <= 2.0 ** -3 * 448
    else:
        assert torch.equal(s.cpu(), s_cpu)
        assert bool(same.all())


@pytest.mark.parametrize("dtype", [torch.float32, torch.bfloat16])
def test_geglu_cuda_equals_cpu(dtype):
    x = torch.randn(3, 50, 2 * 72, generator=torch.Generator().manual_seed(1)).to(dtype)
    y, y_cpu = geglu(x.cuda()).cpu(), geglu(x)
    tol = 1e-6 if dtype == torch.float32 else 2.0 ** -8
    assert torch.allclose(y.float(), y_cpu.float(), rtol=tol, atol=1e-6)


def test_fp8_linear_scaled_mm_equals_emulation():
    _needs_fp8()
    gen = torch.Generator().manual_seed(2)
    lin = torch.nn.Linear(320, 1280).to("cuda", torch.bfloat16)
    x = torch.randn(2, 4096, 320, generator=gen).to("cuda", torch.bfloat16)
    with torch.no_grad():
        y = mk.Fp8Linear(lin)(x).float()
        ref = mk.Fp8Linear(lin, emulate=True)(x.float()).float()  # float32 product of the same operands
        exact = lin.float()(x.float())
    # the quantised operands are the same (the bf16 input quantises as its float32 copy); the
    # difference is the output's bfloat16 rounding plus accumulation order
    assert torch.allclose(y, ref, rtol=2.0 ** -7, atol=1e-3 * float(ref.abs().max()))
    cos = float(torch.nn.functional.cosine_similarity(y.flatten(), exact.flatten(), dim=0))
    assert cos > 0.998


def test_graphed_ip2p_step_with_all_kernels_equals_eager(tiny_models, ip2p_step_inputs):
    _needs_fp8()
    from tiger.edit.guidance.ip2p import InstructPix2PixGuidance, load_ip2p

    ip = load_ip2p(tiny_models / "instruct-pix2pix", device="cuda", dtype=torch.bfloat16)
    kernels = mk.ModelKernels(matmul_precision="fp8", fused_geglu=True, vae_downsample_4x4=True)
    eager = InstructPix2PixGuidance(ip, "make it red", short_side=16, keep_text_encoder=True, kernels=kernels)
    graphed = InstructPix2PixGuidance(ip, "make it red", short_side=16, cuda_graph=True, kernels=kernels)
    assert any(isinstance(m, mk.Fp8Linear) for m in ip.unet.modules())
    for seed in (0, 1):
        torch.manual_seed(seed)
        renders, views, draws = ip2p_step_inputs()
        a, _ = eager.grad(renders, views, **draws)
        b, _ = graphed.grad(renders, views, **draws)
        assert torch.isfinite(a).all() and float(a.abs().max()) > 0
        assert torch.allclose(a, b, rtol=2e-2, atol=2e-2 * float(a.abs().max())), (seed, float((a - b).abs().max()))


@pytest.fixture
def no_tf32():
    """cuDNN runs float32 convolutions in TF32 by default (10-bit mantissa): two algorithms then
    differ by ~1e-3 of the output (seen on the H100), which would hide the kernels' own error."""
    conv, mm = torch.backends.cudnn.allow_tf32, torch.backends.cuda.matmul.allow_tf32
    torch.backends.cudnn.allow_tf32 = torch.backends.cuda.matmul.allow_tf32 = False
    yield
    torch.backends.cudnn.allow_tf32, torch.backends.cuda.matmul.allow_tf32 = conv, mm


def test_graphed_default_kernels_equal_plain_eager_float32(tiny_models, ip2p_step_inputs, no_tf32):
    from tiger.edit.guidance.ip2p import InstructPix2PixGuidance, load_ip2p

    ip = load_ip2p(tiny_models / "instruct-pix2pix", device="cuda")
    plain = mk.ModelKernels(fused_geglu=False, vae_downsample_4x4=False, fold_norm_bias=False, row_layer_norm=False,
                           subpixel_upsample=False, lean_attention=False,
                           block_backward=False, pad_conv_in=False, fused_transformer=False)
    torch.manual_seed(3)
    renders, views, draws = ip2p_step_inputs(t=[30, 80, 130, 190])
    a, _ = InstructPix2PixGuidance(ip, "make it red", short_side=16, keep_text_encoder=True,
                                   kernels=plain).grad(renders, views, **draws)
    graphed = InstructPix2PixGuidance(ip, "make it red", short_side=16, cuda_graph=True)  # the defaults
    assert any("forward" in m.__dict__ for m in ip.unet.modules() if type(m).__name__ == "FeedForward")
    assert any("_tiger_fused_weights" in m.__dict__ for m in ip.unet.modules())  # fused transformer blocks
    b, _ = graphed.grad(renders, views, **draws)
    assert torch.allclose(a, b, rtol=1e-3, atol=1e-3 * float(a.abs().max())), float((a - b).abs().max())
