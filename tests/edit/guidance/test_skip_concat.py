"""The up blocks' skip concatenations written in place (tiger.edit.guidance.skip_concat): the tiny
InstructPix2Pix UNet (an UpBlock2D with an upsampler, then a CrossAttnUpBlock2D) predicts the same
noise bit for bit with it on and off, in float64 and bfloat16, with every producer writing into
the wide map (folded ResNet blocks, fused transformers, the sub-pixel upsampler) and with
producers that cannot (diffusers' own modules: copied in); only the concatenation after the mid
block is left to torch.cat; gradients, FreeU and the switch fall back to diffusers."""
import pytest
import torch

from tiger.edit.guidance import conv_layers, fused_norms
from tiger.edit.guidance import model_kernels as mk
from tiger.edit.guidance import skip_concat as sc
from tiger.edit.guidance import transformer_blocks as tb
from tiger.ops.channel_bias import channel_bias_add

diffusers = pytest.importorskip("diffusers")


def _unet(tiny_models, dtype, fused: bool):
    from tiger.edit.guidance.ip2p import load_ip2p

    unet = load_ip2p(tiny_models / "instruct-pix2pix", fused_norms=fused, dtype=dtype).unet.eval()
    if fused:
        assert fused_norms.set_fold_norm_bias(unet, True) > 0
        assert conv_layers.set_subpixel_upsample(unet, True) == 1
        assert tb.set_fused_transformer(unet, True) > 0
    return unet


def _cats(monkeypatch) -> list[int]:
    """Counts the torch.cat calls on maps (the up blocks'; the UNet's other cats join 1-D or 2-D tensors)."""
    calls: list[int] = []
    real = torch.cat

    def counting(tensors, *args, **kwargs):
        if tensors[0].dim() == 4:
            calls.append(1)
        return real(tensors, *args, **kwargs)

    monkeypatch.setattr(sc.torch, "cat", counting)
    return calls


def _predict(unet, x, t, e):
    with torch.no_grad():
        return unet(x, t, encoder_hidden_states=e).sample


@pytest.mark.parametrize("dtype", [torch.float64, torch.bfloat16])
@pytest.mark.parametrize("fused", [True, False], ids=["producers_write", "copied_in"])
def test_in_place_concatenations_give_the_same_prediction_bit_for_bit(tiny_models, unet_inputs, monkeypatch, dtype,
                                                                     fused):
    unet = _unet(tiny_models, dtype, fused)
    x, t, e = unet_inputs(unet, dtype)
    x = x.contiguous(memory_format=torch.channels_last)
    cats = _cats(monkeypatch)
    want = _predict(unet, x, t, e)
    assert len(cats) == 4  # diffusers: one per up-block ResNet block
    assert sc.set_skip_concat(unet, True) == 2
    copies = []
    monkeypatch.setattr(sc, "channel_bias_add", lambda *a, **k: copies.append(1) or channel_bias_add(*a, **k))
    cats.clear()
    got = _predict(unet, x, t, e)
    assert torch.equal(got, want), (got - want).abs().max()
    if fused:  # torch.cat after the mid block only; three skips copied into wide maps their producers wrote
        assert (len(cats), len(copies)) == (1, 3)
    else:  # diffusers' modules: the ResNet block's and the attention's outputs copied in as well, and
        # the upsampler hands nothing on (a cat)
        assert (len(cats), len(copies)) == (2, 4)
    assert sc.set_skip_concat(unet, False) == 0
    cats.clear()
    assert torch.equal(_predict(unet, x, t, e), want) and len(cats) == 4
    assert all(sc._HANDOFF not in b.__dict__ and "forward" not in b.__dict__ for b in unet.up_blocks)


def test_next_skip_channels_come_from_the_next_blocks_first_resnet(tiny_models):
    unet = _unet(tiny_models, torch.float64, True)
    sc.set_skip_concat(unet, True)
    up0, up1 = unet.up_blocks
    # up1's first ResNet block takes the upsampled 64 channels and a 32-channel skip
    assert up1.resnets[0].in_channels == 96 and up0.__dict__[sc._NEXT_SKIP] == 32
    assert sc._NEXT_SKIP not in up1.__dict__  # the last block hands nothing on


def test_apply_model_kernels_turns_it_on_only_with_cuda_kernels(tiny_models):
    from tiger.edit.guidance.ip2p import load_ip2p

    models = load_ip2p(tiny_models / "instruct-pix2pix")  # CPU: "auto" resolves to off
    assert mk.apply_model_kernels(models.unet, models.vae, mk.ModelKernels())["skip_concat_blocks"] == 0
    assert mk.apply_model_kernels(models.unet, models.vae, mk.ModelKernels(skip_concat=True))["skip_concat_blocks"] == 2


def test_gradients_and_freeu_run_diffusers_forward(tiny_models, unet_inputs, monkeypatch):
    unet = _unet(tiny_models, torch.float64, True)
    x, t, e = unet_inputs(unet, torch.float64)
    x = x.contiguous(memory_format=torch.channels_last)
    want = _predict(unet, x, t, e)
    sc.set_skip_concat(unet, True)
    cats = _cats(monkeypatch)
    xr = x.clone().requires_grad_()
    y = unet(xr, t, encoder_hidden_states=e).sample  # with a gradient: diffusers' blocks (4 cats)
    torch.testing.assert_close(y, want, rtol=1e-12, atol=1e-12)
    y.square().sum().backward()
    assert len(cats) == 4 and torch.isfinite(xr.grad).all() and xr.grad.abs().sum() > 0
    cats.clear()
    unet.enable_freeu(s1=0.9, s2=0.2, b1=1.2, b2=1.4)
    freeu = _predict(unet, x, t, e)
    assert len(cats) == 4
    sc.set_skip_concat(unet, False)
    assert torch.equal(freeu, _predict(unet, x, t, e))


@pytest.mark.cuda
@pytest.mark.skipif(not (torch.cuda.is_available() and __import__("tiger").ops.cuda_enabled()),
                    reason="needs a CUDA device and tiger built with CUDA")
@pytest.mark.parametrize("dtype", [torch.bfloat16, torch.float32])
def test_cuda_default_kernels_with_and_without_in_place_concatenations_agree_bit_for_bit(tiny_models, unet_inputs,
                                                                                         monkeypatch, dtype):
    from tiger.edit.guidance.ip2p import load_ip2p

    models = load_ip2p(tiny_models / "instruct-pix2pix", device="cuda", dtype=dtype)
    unet = models.unet.eval()
    got = mk.apply_model_kernels(unet, models.vae, mk.ModelKernels())
    assert got["skip_concat_blocks"] == 2 and got["subpixel_upsamples"] == 1 and got["fused_transformer_blocks"] > 0
    x, t, e = (v.cuda() for v in unet_inputs(unet, dtype))
    x = x.contiguous(memory_format=torch.channels_last)
    cats = _cats(monkeypatch)
    on = _predict(unet, x, t, e)
    assert len(cats) == 1
    mk.apply_model_kernels(unet, models.vae, mk.ModelKernels(skip_concat=False))
    assert torch.equal(on, _predict(unet, x, t, e)) and len(cats) == 5
    assert torch.isfinite(on).all()
