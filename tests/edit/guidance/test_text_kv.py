"""The cross-attentions' keys and values of a fixed text, computed once (tiger.edit.guidance.text_kv):
the tiny InstructPix2Pix UNet (float64) predicts the same with them kept, through the fused
transformer blocks and through the lean attention processor; the projections run on the first
call only; a changed text or weight, gradients and the switch recompute; branch_text keeps one
tensor per branch layout."""
import pytest
import torch

from tiger.edit.guidance import transformer_blocks as tb
from tiger.edit.guidance.text_kv import branch_text, memo_text_kv

diffusers = pytest.importorskip("diffusers")


class _Owner:
    pass


@pytest.fixture
def unet64(tiny_ip2p):
    unet = tiny_ip2p.unet.double()
    tb.set_lean_attention(unet, True)
    yield unet
    tb.set_cached_text_kv(unet, False)
    tb.set_fused_transformer(unet, False)
    unet.float()


def _count_text_projections(unet, monkeypatch) -> list[int]:
    """Calls that project text: the lean processor's attn2.to_k, or a fused block's stacked k/v matmul."""
    calls: list[int] = []
    for m in unet.modules():
        if type(m).__name__ == "Attention" and m.is_cross_attention:
            m.to_k.register_forward_hook(lambda *a: calls.append(1))
    kv = {id(m.__dict__["_tiger_fused_weights"].kv_weight) for m in unet.modules() if "_tiger_fused_weights" in m.__dict__}
    real = tb.F.linear
    monkeypatch.setattr(tb.F, "linear", lambda x, w, b=None: (calls.append(1) if id(w) in kv else None) or real(x, w, b))
    return calls


def _inputs(unet, owner):
    gen = torch.Generator().manual_seed(8)
    x = torch.randn(3, unet.config.in_channels, 8, 8, generator=gen, dtype=torch.float64)
    text = torch.randn(2, 77, unet.config.cross_attention_dim, generator=gen, dtype=torch.float64)
    return x, torch.tensor([10, 200, 900]), text, branch_text(owner, text, (1, 2))


@pytest.mark.parametrize("fused", [False, True])
def test_kept_keys_and_values_give_the_same_prediction(unet64, fused, monkeypatch):
    unet, owner = unet64, _Owner()
    n_fused = tb.set_fused_transformer(unet, fused)
    x, t, text, e = _inputs(unet, owner)
    with torch.no_grad():
        want = unet(x, t, encoder_hidden_states=e).sample
        n_cross = sum(1 for m in unet.modules() if type(m).__name__ == "Attention" and m.is_cross_attention)
        assert tb.set_cached_text_kv(unet, True) == n_cross > 0
        assert (n_fused > 0) == fused
        calls = _count_text_projections(unet, monkeypatch)
        first = unet(x, t, encoder_hidden_states=e).sample
        assert len(calls) == n_cross
        again = unet(x, t, encoder_hidden_states=branch_text(owner, text, (1, 2))).sample  # the same tensor
        assert len(calls) == n_cross  # nothing projected the second time
    torch.testing.assert_close(first, want, rtol=1e-12, atol=1e-12)
    assert torch.equal(again, first)


@pytest.mark.parametrize("fused", [False, True])
def test_a_changed_text_or_weight_is_projected_again(unet64, fused, monkeypatch):
    unet, owner = unet64, _Owner()
    tb.set_fused_transformer(unet, fused)
    tb.set_cached_text_kv(unet, True)
    x, t, text, e = _inputs(unet, owner)

    def fresh():  # the reference: nothing kept
        tb.set_cached_text_kv(unet, False)
        y = unet(x, t, encoder_hidden_states=e.clone()).sample
        tb.set_cached_text_kv(unet, True)
        return y

    with torch.no_grad():
        unet(x, t, encoder_hidden_states=e)
        e.mul_(1.5)  # in place: the text's version counter
        torch.testing.assert_close(unet(x, t, encoder_hidden_states=e).sample, fresh(), rtol=1e-12, atol=1e-12)
        attn2 = unet.down_blocks[0].attentions[0].transformer_blocks[0].attn2
        attn2.to_v.weight.add_(torch.randn(attn2.to_v.weight.shape, generator=torch.Generator().manual_seed(2),
                                           dtype=torch.float64))
        torch.testing.assert_close(unet(x, t, encoder_hidden_states=e).sample, fresh(), rtol=1e-12, atol=1e-12)
    # another text tensor is another memo
    calls = _count_text_projections(unet, monkeypatch)
    with torch.no_grad():
        unet(x, t, encoder_hidden_states=e.clone())
    assert len(calls) > 0


def test_gradients_keep_nothing(unet64):
    unet, owner = unet64, _Owner()
    tb.set_cached_text_kv(unet, True)
    x, t, text, e = _inputs(unet, owner)
    unet(x, t, encoder_hidden_states=e).sample.sum()
    assert "_tiger_text_kv" not in e.__dict__
    with torch.no_grad():
        unet(x, t, encoder_hidden_states=e)
    assert len(e.__dict__["_tiger_text_kv"]) > 0


def test_memo_checks_its_weights():
    text, w1, w2 = torch.randn(3, 4), torch.randn(5, 4), torch.randn(5, 4)
    layer, calls = object(), []

    def compute(w):
        calls.append(1)
        return text @ w.t(), text @ w.t()

    with torch.no_grad():
        k1, _ = memo_text_kv(layer, text, [w1], lambda: compute(w1))
        assert memo_text_kv(layer, text, [w1], lambda: compute(w1))[0] is k1
        k2, _ = memo_text_kv(layer, text, [w2], lambda: compute(w2))  # other weights: computed
        w2.mul_(2)
        k3, _ = memo_text_kv(layer, text, [w2], lambda: compute(w2))  # changed in place: computed
    assert len(calls) == 3
    torch.testing.assert_close(k3, 2 * k2)


def test_branch_text_keeps_one_tensor_per_layout():
    owner, e = _Owner(), torch.randn(2, 5, 8)
    a = branch_text(owner, e, (2, 4))
    assert branch_text(owner, e, (2, 4)) is a and a.shape == (6, 5, 8)
    assert torch.equal(a[:2], e[:1].expand(2, -1, -1)) and torch.equal(a[2:], e[1:].expand(4, -1, -1))
    assert branch_text(owner, e, (1, 1)) is not a
    e.add_(1)
    b = branch_text(owner, e, (2, 4))
    assert b is not a and torch.equal(b[0], e[0])
    with pytest.raises(ValueError, match="one count per text row"):
        branch_text(owner, e, (1, 2, 3))
