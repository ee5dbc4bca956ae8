"""The stacked time-embedding biases (tiger.edit.guidance.time_bias): the tiny InstructPix2Pix
UNet with folded norms gives the same noise predictions (float64) with its blocks' biases from
one stacked matmul, with the shared branch prefix too; the blocks' own projections no longer run;
in-place weight changes, gradients and the switch fall back or re-derive as documented."""
import pytest
import torch

from tiger.edit.guidance import branch_prefix as bp
from tiger.edit.guidance import fused_norms
from tiger.edit.guidance import time_bias as tbias

diffusers = pytest.importorskip("diffusers")


@pytest.fixture
def folded_unet(tiny_models):
    from tiger.edit.guidance.ip2p import load_ip2p

    unet = load_ip2p(tiny_models / "instruct-pix2pix", fused_norms=True, dtype=torch.float64).unet
    assert fused_norms.set_fold_norm_bias(unet, True) > 0
    return unet


def _projections_called(monkeypatch) -> list[int]:
    calls: list[int] = []
    real = fused_norms.SiLUThenLinear.forward
    monkeypatch.setattr(fused_norms.SiLUThenLinear, "forward", lambda self, x: calls.append(1) or real(self, x))
    return calls


def _predict(unet, x, t, e, share=None):
    with torch.no_grad():
        if share is None:
            return unet(x, t, encoder_hidden_states=e).sample
        with bp.shared_branches(unet, share):
            return unet(x, t, encoder_hidden_states=e).sample


def test_stacked_biases_give_the_same_prediction_float64(folded_unet, unet_inputs, monkeypatch):
    unet = folded_unet
    x, t, e = unet_inputs(unet, torch.float64)
    x = x.contiguous(memory_format=torch.channels_last)
    want = _predict(unet, x, t, e)
    blocks = [m for m in unet.modules() if type(m).__name__ == "ResnetBlock2D" and m.time_emb_proj is not None]
    assert tbias.set_stacked_time_bias(unet, True) == len(blocks) > 2
    calls = _projections_called(monkeypatch)
    got = _predict(unet, x, t, e)
    assert calls == []  # every block read its bias from the stacked matmul
    torch.testing.assert_close(got, want, rtol=1e-12, atol=1e-12)
    # the stacked weights follow an in-place change of a block's projection
    with torch.no_grad():  # not a constant: norm2 would take a shift of every channel away
        w = blocks[1].time_emb_proj.weight
        w.add_(torch.randn(w.shape, generator=torch.Generator().manual_seed(1), dtype=w.dtype))
    changed = _predict(unet, x, t, e)
    assert tbias.set_stacked_time_bias(unet, False) == 0
    torch.testing.assert_close(changed, _predict(unet, x, t, e), rtol=1e-12, atol=1e-12)
    assert not torch.allclose(changed, want)
    assert len(calls) == len(blocks)  # switched off: the blocks' own projections again


def test_stacked_biases_with_the_shared_branch_prefix(folded_unet, monkeypatch):
    """The prefix's first block gets a compacted temb (a second cached entry); the prediction is
    the one without either."""
    unet = folded_unet
    gen = torch.Generator().manual_seed(4)
    v, c = 2, unet.config.in_channels // 2
    z, cond = torch.randn(v, c, 8, 8, generator=gen, dtype=torch.float64), torch.randn(v, c, 8, 8, generator=gen,
                                                                                      dtype=torch.float64)
    x = torch.cat([torch.cat([z, z, z]), torch.cat([cond, cond, torch.zeros_like(cond)])], 1)
    x = x.contiguous(memory_format=torch.channels_last)
    t = torch.tensor([30, 170]).repeat(3)
    text = torch.randn(2, 5, unet.config.cross_attention_dim, generator=gen, dtype=torch.float64)
    e = torch.cat([text[:1].expand(v, -1, -1), text[1:].expand(2 * v, -1, -1)])
    want = _predict(unet, x, t, e)
    try:
        bp.set_branch_prefix(unet, True)
        tbias.set_stacked_time_bias(unet, True)
        calls = _projections_called(monkeypatch)
        got = _predict(unet, x, t, e, bp.BranchShare(v, v))
        assert calls == []
    finally:
        bp.set_branch_prefix(unet, False)
        tbias.set_stacked_time_bias(unet, False)
    torch.testing.assert_close(got, want, rtol=1e-12, atol=1e-12)


def test_gradients_and_unfolded_blocks_keep_their_own_projection(folded_unet, unet_inputs, monkeypatch):
    unet = folded_unet
    x, t, e = unet_inputs(unet, torch.float64)
    tbias.set_stacked_time_bias(unet, True)
    calls = _projections_called(monkeypatch)
    try:
        unet.time_embedding.linear_1.weight.requires_grad_(True)  # a gradient through temb is asked for
        y = unet(x, t, encoder_hidden_states=e).sample
        (g,) = torch.autograd.grad(y.sum(), unet.time_embedding.linear_1.weight)
        assert torch.isfinite(g).all() and g.abs().sum() > 0
        n_blocks = len(calls)
        assert n_blocks > 2
        unet.time_embedding.linear_1.weight.requires_grad_(False)
        fused_norms.set_fold_norm_bias(unet, False)  # not folded: conv1's bias pass, the block's own projection
        calls.clear()
        _predict(unet, x, t, e)
        assert len(calls) == n_blocks
    finally:
        tbias.set_stacked_time_bias(unet, False)


def test_a_unet_without_folded_blocks_shares_nothing(tiny_models):
    from tiger.edit.guidance.ip2p import load_ip2p

    unet = load_ip2p(tiny_models / "instruct-pix2pix", fused_norms=False).unet
    assert tbias.set_stacked_time_bias(unet, True) == 0
