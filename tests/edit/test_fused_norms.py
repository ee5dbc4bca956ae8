"""fuse_group_norms / apply_fused_norms on tiny random diffusers models of the real block types:
same outputs and input gradients as the unpatched models (fp32), every norm replaced and fed
channels-last, the SiLU moves handled per ResnetBlock2D variant, and the loaders' option."""
import copy

import pytest
import torch
import torch.nn.functional as F

from tiger.edit.guidance.fused_norms import (SiLUThenLinear, apply_fused_norms, bias_after_conv, fuse_group_norms,
                                             fused_norms_default)
from tiger.testing.random_models import ip2p_unet_config, mvdream_ldm_config, sd_vae_config
from tiger.ops.group_norm import GroupNormSiLU

diffusers = pytest.importorskip("diffusers")
CL = torch.channels_last


def _is_cl(t):
    return t.is_contiguous(memory_format=CL) and not t.is_contiguous()


def _fused_copy(model):
    fused = copy.deepcopy(model)
    n_plain = sum(type(m) is torch.nn.GroupNorm for m in fused.modules())
    assert apply_fused_norms(fused, True) == n_plain > 0
    assert not any(type(m) is torch.nn.GroupNorm for m in fused.modules())
    assert fuse_group_norms(fused) == 0  # idempotent
    convs = [m for m in fused.modules() if type(m) is torch.nn.Conv2d and m.bias is not None]
    assert convs and all("forward" in m.__dict__ for m in convs)  # bias added by tiger's op
    assert bias_after_conv(fused) == 0
    assert set(fused.state_dict()) == set(model.state_dict())
    layouts = []
    for m in fused.modules():
        if isinstance(m, GroupNormSiLU):
            m.register_forward_pre_hook(lambda mod, args: layouts.append(
                _is_cl(args[0].unsqueeze(-1) if args[0].dim() == 3 else args[0])))
    return fused, layouts


def _same_outputs_and_input_grads(run, model, fused, inp, layouts):
    a, b = inp.clone().requires_grad_(), inp.clone().requires_grad_()
    out_a, out_b = run(model, a), run(fused, b)
    torch.testing.assert_close(out_b, out_a, atol=2e-5, rtol=2e-5)
    g = torch.randn(out_a.shape, generator=torch.Generator().manual_seed(3))
    (out_a * g).sum().backward()
    (out_b * g).sum().backward()
    torch.testing.assert_close(b.grad, a.grad, atol=2e-5, rtol=2e-5)
    assert layouts and all(layouts), "a fused norm saw a non-channels-last input"


def test_vae_encoder_patched_equals_plain():
    torch.manual_seed(0)
    vae = diffusers.AutoencoderKL(**sd_vae_config("tiny")).eval()
    fused, layouts = _fused_copy(vae)
    assert isinstance(fused.encoder.conv_norm_out, GroupNormSiLU) and fused.encoder.conv_norm_out.silu
    assert isinstance(fused.encoder.conv_act, torch.nn.Identity)
    assert not fused.encoder.mid_block.attentions[0].group_norm.silu
    x = torch.rand(2, 3, 16, 16)
    _same_outputs_and_input_grads(lambda m, t: m.encode(t).latent_dist.mean, vae, fused, x, layouts)


@pytest.mark.parametrize("kind", ["ip2p", "mvdream"])
def test_unet_patched_equals_plain(kind):
    from tiger.edit.guidance.ldm_checkpoint import unet_config_from_ldm

    torch.manual_seed(1)
    cfg = ip2p_unet_config("tiny") if kind == "ip2p" else unet_config_from_ldm(mvdream_ldm_config("tiny"))
    unet = diffusers.UNet2DConditionModel(**cfg).eval()
    fused, layouts = _fused_copy(unet)
    block = fused.down_blocks[0].resnets[0]
    assert block.norm1.silu and block.norm2.silu and isinstance(block.nonlinearity, torch.nn.Identity)
    assert isinstance(block.time_emb_proj, SiLUThenLinear)
    n = 4
    t = torch.tensor([10, 300, 600, 900])
    emb = torch.randn(n, 77, cfg["cross_attention_dim"])
    extra = {}
    if cfg.get("class_embed_type") == "projection":
        extra["class_labels"] = torch.randn(n, cfg["projection_class_embeddings_input_dim"])
    x = torch.randn(n, cfg["in_channels"], 8, 8)
    _same_outputs_and_input_grads(lambda m, inp: m(inp, t, encoder_hidden_states=emb, **extra).sample,
                                  unet, fused, x, layouts)


@pytest.mark.parametrize("variant", [dict(), dict(skip_time_act=True), dict(time_embedding_norm="scale_shift"),
                                     dict(non_linearity="mish"), dict(temb_channels=None)])
def test_resnet_block_variants(variant):
    from diffusers.models.resnet import ResnetBlock2D

    torch.manual_seed(2)
    kw = dict(in_channels=16, out_channels=24, temb_channels=12, groups=4, eps=1e-6)
    kw.update(variant)
    block = ResnetBlock2D(**kw).eval()
    fused = copy.deepcopy(block)
    assert fuse_group_norms(fused) == 2
    fusable = variant in (dict(), dict(skip_time_act=True), dict(temb_channels=None))
    assert fused.norm1.silu == fused.norm2.silu == fusable
    assert isinstance(fused.nonlinearity, torch.nn.Identity) == fusable
    assert isinstance(fused.time_emb_proj, SiLUThenLinear) == (variant == dict())
    x = torch.randn(2, 16, 6, 6)
    temb = None if kw["temb_channels"] is None else torch.randn(2, 12)
    torch.testing.assert_close(fused(x, temb), block(x, temb), atol=1e-5, rtol=1e-5)


def test_silu_then_linear_shares_parameters():
    lin = torch.nn.Linear(5, 3)
    m = SiLUThenLinear.from_linear(lin)
    assert m.weight is lin.weight and m.bias is lin.bias
    x = torch.randn(4, 5)
    torch.testing.assert_close(m(x), lin(F.silu(x)))


def test_loader_option_gives_the_same_gradient(tiny_models):
    from tiger.edit.guidance.ip2p import InstructPix2PixGuidance, load_ip2p
    from tiger.edit.guidance.diffusers_models import is_channels_last

    plain = load_ip2p(tiny_models / "instruct-pix2pix")
    fused = load_ip2p(tiny_models / "instruct-pix2pix", fused_norms=True)
    assert not is_channels_last(plain.vae) and is_channels_last(fused.vae) and is_channels_last(fused.unet)
    assert any(isinstance(m, GroupNormSiLU) for m in fused.vae.modules())
    grads = []
    for models in (plain, fused):
        g = InstructPix2PixGuidance(models, "make it red", short_side=16)
        gen = torch.Generator().manual_seed(0)
        renders, originals = torch.rand(4, 3, 16, 16, generator=gen), torch.rand(4, 3, 16, 16, generator=gen)
        size = g.resolution(16, 16)
        cond = g.condition_latents(originals, size)
        noise = torch.randn(cond.shape, generator=gen)
        vae_noise = torch.randn(cond.shape, generator=gen)
        grads.append(g.step(renders, cond, torch.tensor([20, 60, 120, 180]), noise, vae_noise))
    assert grads[1].is_contiguous()
    torch.testing.assert_close(grads[1], grads[0], atol=1e-6, rtol=1e-4)


def test_default_is_off_on_the_cpu(tiny_models):
    from tiger.edit.guidance.ip2p import load_ip2p

    m = load_ip2p(tiny_models / "instruct-pix2pix")  # fused_norms=None on the CPU: nothing changes
    assert not fused_norms_default(m.vae) and not fused_norms_default(m.unet)
    assert apply_fused_norms(m.vae) == 0 and not any(isinstance(x, GroupNormSiLU) for x in m.vae.modules())


@pytest.mark.skipif(not torch.cuda.is_available(), reason="CUDA")
def test_default_on_cuda_fuses_vae_and_unet_not_the_text_encoder(tiny_models):
    from tiger.edit.guidance.ip2p import load_ip2p
    from tiger.ops import cuda_enabled

    if not cuda_enabled():
        pytest.skip("tiger built without its CUDA kernels")
    m = load_ip2p(tiny_models / "instruct-pix2pix", device="cuda")
    for model in (m.vae, m.unet):
        assert fused_norms_default(model)
        assert any(isinstance(x, GroupNormSiLU) for x in model.modules())
        assert not any(type(x) is torch.nn.GroupNorm for x in model.modules())
    assert not fused_norms_default(torch.nn.Linear(2, 2).cuda())
