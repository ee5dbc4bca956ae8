"""The shared branch prefix (tiger.edit.guidance.branch_prefix): InstructPix2Pix's tiny UNet on the
3-branch batch gives the same noise predictions with the instruction and image-only rows computed
once up to the first cross-attention (fused transformer blocks or diffusers' own), its fallbacks,
the row bookkeeping and the switch."""
import pytest
import torch

from tiger.edit.guidance import branch_prefix as bp
from tiger.edit.guidance import transformer_blocks as tb

diffusers = pytest.importorskip("diffusers")


def _branch_inputs(unet, v=2, dtype=torch.float64):
    """A 3-branch InstructPix2Pix batch: rows [v, 2v) repeat rows [0, v) except for the text."""
    gen = torch.Generator().manual_seed(3)
    c = unet.config.in_channels // 2
    z = torch.randn(v, c, 8, 8, generator=gen, dtype=dtype)
    cond = torch.randn(v, c, 8, 8, generator=gen, dtype=dtype)
    x = torch.cat([torch.cat([z, z, z]), torch.cat([cond, cond, torch.zeros_like(cond)])], 1)
    t = torch.randint(20, 200, (v,), generator=gen).repeat(3)
    d = unet.config.cross_attention_dim
    text = torch.randn(2, 5, d, generator=gen, dtype=dtype)
    emb = torch.cat([text[:1].expand(v, -1, -1), text[1:].expand(2 * v, -1, -1)])
    return x, t, emb


@pytest.mark.parametrize("fused", [False, True])
def test_shared_prefix_gives_the_same_prediction(tiny_ip2p, fused, monkeypatch):
    halves = []
    real = bp.fused_self_attention
    monkeypatch.setattr(bp, "fused_self_attention", lambda block, d, x: halves.append(x.shape[0]) or real(block, d, x))
    unet = tiny_ip2p.unet.double()
    try:
        tb.set_fused_transformer(unet, fused)
        x, t, emb = _branch_inputs(unet)
        with torch.no_grad():
            want = unet(x, t, encoder_hidden_states=emb).sample
            assert bp.set_branch_prefix(unet, True) == 1
            calls = []
            first = unet.down_blocks[0].resnets[0]
            hook = first.register_forward_hook(lambda m, args, out: calls.append(args[0].shape[0]))
            with bp.shared_branches(unet, bp.BranchShare(2, 2)):
                got = unet(x, t, encoder_hidden_states=emb).sample
            hook.remove()
        assert calls == [4]  # the first ResNet block ran on the 4 rows that differ, not 6
        assert halves == ([4] if fused else [])  # and, fused, the first self-attention
        torch.testing.assert_close(got, want, rtol=1e-10, atol=1e-12)
    finally:
        bp.set_branch_prefix(unet, False)
        tb.set_fused_transformer(unet, False)
        unet.float()


def test_without_a_share_or_switched_off_all_rows_run(tiny_ip2p):
    unet = tiny_ip2p.unet
    x, t, emb = _branch_inputs(unet, dtype=torch.float32)
    calls = []
    hook = unet.down_blocks[0].resnets[0].register_forward_hook(lambda m, args, out: calls.append(args[0].shape[0]))
    try:
        with torch.no_grad():
            bp.set_branch_prefix(unet, True)
            unet(x, t, encoder_hidden_states=emb)  # no share set: diffusers' forward
            bp.set_branch_prefix(unet, False)
            with bp.shared_branches(unet, bp.BranchShare(2, 2)):  # switched off: the share is ignored
                unet(x, t, encoder_hidden_states=emb)
            bp.set_branch_prefix(unet, True)
            with torch.enable_grad(), bp.shared_branches(unet, bp.BranchShare(2, 2)):  # gradients: fallback
                unet(x, t, encoder_hidden_states=emb)
    finally:
        hook.remove()
        bp.set_branch_prefix(unet, False)
    assert calls == [6, 6, 6]
    assert "_tiger_branch_share" not in unet.down_blocks[0].__dict__  # the context cleaned up


def test_compact_and_expand_rows():
    share = bp.BranchShare(2, 2)
    x = torch.tensor([0, 1, 0, 1, 5, 6])
    assert share.compact(x).tolist() == [0, 1, 5, 6]
    assert share.expand(share.compact(x)).tolist() == x.tolist()
    with pytest.raises(ValueError, match="BranchShare"):
        bp.BranchShare(1, 2)


def test_model_kernels_put_the_prefix_on_by_default(tiny_ip2p):
    from tiger.edit.guidance import model_kernels as mk

    unet, vae = tiny_ip2p.unet, tiny_ip2p.vae
    try:
        assert mk.apply_model_kernels(unet, vae, mk.ModelKernels())["branch_prefix_blocks"] == 1
        assert "forward" in unet.down_blocks[0].__dict__
        assert mk.apply_model_kernels(unet, vae, mk.ModelKernels(branch_prefix=False))["branch_prefix_blocks"] == 0
        assert "forward" not in unet.down_blocks[0].__dict__
    finally:
        mk.apply_model_kernels(unet, vae, mk.ModelKernels(branch_prefix=False))


@pytest.mark.parametrize("fused", [False, True])
def test_mvdream_branches_share_their_prefix(mvdream_unet64, mvdream_inputs, fused, monkeypatch):
    """MVDream's prompt and negative-prompt branches (same latents, t and cameras) agree until the
    first cross-attention: its first ResNet block (and, fused, its multi-view self-attention over
    the one group of 4 views left) runs on 4 of the 8 rows, with the same noise prediction."""
    halves = []
    real = bp.fused_self_attention
    monkeypatch.setattr(bp, "fused_self_attention", lambda block, d, x: halves.append(x.shape[0]) or real(block, d, x))
    unet = mvdream_unet64
    tb.set_fused_transformer(unet, fused)
    x, t, emb, cams2 = mvdream_inputs(unet)
    with torch.no_grad():
        want = unet(x, t, encoder_hidden_states=emb, class_labels=cams2).sample
        assert bp.set_branch_prefix(unet, True) == 1
        calls = []
        hook = unet.down_blocks[0].resnets[0].register_forward_hook(lambda m, args, out: calls.append(args[0].shape[0]))
        with bp.shared_branches(unet, bp.BranchShare(4, 4)):
            got = unet(x, t, encoder_hidden_states=emb, class_labels=cams2).sample
        hook.remove()
    assert calls == [4]
    assert halves == ([4] if fused else [])
    torch.testing.assert_close(got, want, rtol=1e-10, atol=1e-12)


def test_the_mvdream_guidance_shares_the_prefix(tiny_models, monkeypatch):
    """MVDreamGuidance's UNet call sets the share (rows [V, 2V) repeat rows [0, V))."""
    from tiger.edit.guidance.mvdream import MVDreamGuidance, load_mvdream

    seen = []
    real = bp._shared_down_block_forward
    monkeypatch.setattr(bp, "_shared_down_block_forward",
                        lambda self, *a, **k: seen.append(self.__dict__.get("_tiger_branch_share")) or real(self, *a, **k))
    guidance = MVDreamGuidance(load_mvdream(tiny_models / "mvdream"), "a tiger", cuda_graph=False)
    bp.set_branch_prefix(guidance.models.unet, False)
    bp.set_branch_prefix(guidance.models.unet, True)  # bound again: to the patched forward
    z = torch.randn(4, 4, 8, 8)
    guidance.latent_grad(z, torch.randn(4, 16), torch.tensor([300]), torch.randn(4, 4, 8, 8))
    assert seen == [bp.BranchShare(4, 4)]
