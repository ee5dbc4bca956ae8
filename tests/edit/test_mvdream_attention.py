"""MVDream's multi-view self-attention processor against independent attention computations."""
import pytest
import torch

diffusers = pytest.importorskip("diffusers")
from diffusers.models.attention_processor import Attention, AttnProcessor  # noqa: E402

from tiger.edit.guidance.mvdream_attention import MultiViewAttnProcessor, install_multiview_attention  # noqa: E402


def _attention(seed=0):
    torch.manual_seed(seed)
    return Attention(query_dim=32, heads=2, dim_head=16).eval()


def _joint_reference(attn, x, views):
    # softmax(QK^T/sqrt(d))V over the tokens of each group of `views` samples, written out.
    bf, l, c = x.shape
    h = x.reshape(bf // views, views * l, c)
    q, k, v = attn.to_q(h), attn.to_k(h), attn.to_v(h)
    split = lambda t: t.reshape(t.shape[0], t.shape[1], attn.heads, -1).transpose(1, 2)  # noqa: E731
    q, k, v = split(q), split(k), split(v)
    w = torch.softmax(q @ k.transpose(-1, -2) / q.shape[-1] ** 0.5, dim=-1)
    out = (w @ v).transpose(1, 2).reshape(h.shape[0], h.shape[1], -1)
    return attn.to_out[0](out).reshape(bf, l, c)


def test_one_view_equals_default_attention():
    attn = _attention()
    x = torch.randn(3, 10, 32)
    with torch.no_grad():
        attn.set_processor(AttnProcessor())
        want = attn(x)
        attn.set_processor(MultiViewAttnProcessor(1))
        got = attn(x)
    assert torch.allclose(got, want, atol=1e-5)


def test_four_views_attend_jointly():
    attn = _attention()
    x = torch.randn(8, 10, 32)  # 2 samples x 4 views
    attn.set_processor(MultiViewAttnProcessor(4))
    with torch.no_grad():
        got = attn(x)
        assert torch.allclose(got, _joint_reference(attn, x, 4), atol=1e-5)
        y = x.clone()
        y[3] += 1.0  # change view 3 of sample 0
        changed = attn(y)
        assert not torch.allclose(changed[0], got[0], atol=1e-4)  # view 0 sees view 3
        assert torch.allclose(changed[4:], got[4:], atol=1e-6)  # the other sample does not
        attn.set_processor(AttnProcessor())
        assert torch.allclose(attn(y)[0], attn(x)[0], atol=1e-6)  # per-view attention would not
    with pytest.raises(ValueError, match="multiple of num_views"):
        attn.set_processor(MultiViewAttnProcessor(4))
        attn(torch.randn(6, 10, 32))


def test_installed_on_self_attention_only():
    from tiger.edit.guidance.ldm_checkpoint import unet_config_from_ldm
    from tiger.testing.random_models import mvdream_ldm_config

    unet = diffusers.UNet2DConditionModel(**unet_config_from_ldm(mvdream_ldm_config("tiny")))
    n = install_multiview_attention(unet, 4)
    procs = unet.attn_processors
    assert n == sum(name.endswith("attn1.processor") for name in procs) > 0
    assert all(isinstance(p, MultiViewAttnProcessor) == name.endswith("attn1.processor") for name, p in procs.items())
