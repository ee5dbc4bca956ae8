"""The VAE attention's softmax by tiger's row kernel (ModelKernels.row_softmax,
diffusers_models.set_row_softmax): the switch finds the matmul attentions and leaves others
alone; the tiny VAE encoder's output and its input gradient equal torch's softmax path (CPU:
the same op; CUDA, bf16: within the float32 summation order's reach)."""
import pytest
import torch

from tiger.edit.guidance import diffusers_models as dm
from tiger.edit.guidance import model_kernels as mk
from tiger.ops.softmax import softmax_rows
from tiger.edit.guidance.diffusers_models import ROW_SOFTMAX, matmul_vae_attention, set_row_softmax

diffusers = pytest.importorskip("diffusers")

CUDA = torch.cuda.is_available() and __import__("tiger").ops.cuda_enabled()


def _encode_and_grad(vae, x):
    x = x.clone().requires_grad_()
    z = vae.encode(x).latent_dist.mean
    (g,) = torch.autograd.grad(z.square().sum(), x)
    return z.detach(), g


def _vae(tiny_models, device="cpu", dtype=torch.float64):
    from tiger.edit.guidance.ip2p import load_ip2p

    vae = load_ip2p(tiny_models / "instruct-pix2pix", device=device, dtype=dtype).vae
    return vae


def test_switch_counts_the_matmul_attentions_and_keeps_values(tiny_models, monkeypatch):
    vae = _vae(tiny_models)
    assert set_row_softmax(vae, True) == 0  # diffusers' processor: nothing to switch
    layers = matmul_vae_attention(vae)
    assert layers >= 1
    x = torch.rand(2, 3, 32, 32, generator=torch.Generator().manual_seed(3), dtype=torch.float64)
    want = _encode_and_grad(vae, x)
    calls = []
    monkeypatch.setattr(dm, "softmax_rows", lambda s: calls.append(s.shape) or softmax_rows(s))
    assert set_row_softmax(vae, True) == layers
    got = _encode_and_grad(vae, x)
    assert len(calls) == layers
    torch.testing.assert_close(got[0], want[0], rtol=1e-13, atol=1e-15)
    torch.testing.assert_close(got[1], want[1], rtol=1e-12, atol=1e-14)
    assert set_row_softmax(vae, False) == 0
    assert all(not m.__dict__.get(ROW_SOFTMAX, False) for m in vae.modules())


def test_apply_model_kernels_leaves_it_off_on_the_cpu(tiny_models):
    from tiger.edit.guidance.ip2p import load_ip2p

    models = load_ip2p(tiny_models / "instruct-pix2pix")
    matmul_vae_attention(models.vae)
    assert mk.apply_model_kernels(models.unet, models.vae, mk.ModelKernels())["row_softmax_layers"] == 0
    assert mk.apply_model_kernels(models.unet, models.vae, mk.ModelKernels(row_softmax=True))["row_softmax_layers"] >= 1


@pytest.mark.cuda
@pytest.mark.skipif(not CUDA, reason="needs a CUDA device and tiger built with CUDA")
def test_cuda_bf16_encoder_and_its_input_gradient_match_torch_softmax(tiny_models):
    vae = _vae(tiny_models, "cuda", torch.bfloat16)
    layers = matmul_vae_attention(vae)
    x = torch.rand(2, 3, 64, 64, generator=torch.Generator().manual_seed(4)).to("cuda", torch.bfloat16)
    want = _encode_and_grad(vae, x)
    assert set_row_softmax(vae, True) == layers
    got = _encode_and_grad(vae, x)
    for a, b in zip(got, want):
        assert torch.isfinite(a).all()
        rel = float((a.float() - b.float()).norm() / b.float().norm())
        assert rel < 2e-2, rel  # bf16 outputs of float32 sums in another order
