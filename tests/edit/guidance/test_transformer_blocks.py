"""The UNets' transformer layers (tiger.edit.guidance.transformer_blocks): the lean attention and
the fused transformer blocks against diffusers' own forward (float64, the tiny InstructPix2Pix
UNet), the fused blocks' bias column (exactly 1 in every dtype), their fallbacks, in-place
semantics, re-derivation and eligibility."""
import copy

import pytest
import torch
import torch.nn.functional as F

from tiger.edit.guidance import model_kernels as mk
from tiger.edit.guidance import transformer_blocks as tb
from tiger.ops.fp8_rows import geglu

diffusers = pytest.importorskip("diffusers")


def _blocks(unet):
    from diffusers.models.attention import BasicTransformerBlock

    return [m for m in unet.modules() if type(m) is BasicTransformerBlock]


def test_lean_attention_gives_the_same_values(tiny_ip2p, unet_inputs):
    from diffusers.models.attention_processor import Attention

    unet = tiny_ip2p.unet
    x, t, e = unet_inputs(unet)
    attns = [m for m in unet.modules() if isinstance(m, Attention)]
    tb.set_lean_attention(unet, False)
    with torch.no_grad():
        y0 = unet(x, t, encoder_hidden_states=e).sample
        assert tb.set_lean_attention(unet, True) == len(attns) > 0
        assert tb.set_lean_attention(unet, True) == len(attns)  # idempotent: no wrapper around a wrapper
        y1 = unet(x, t, encoder_hidden_states=e).sample
    assert torch.equal(y1, y0)  # the same operations, minus a division by 1
    assert tb.set_lean_attention(unet, False) == 0
    assert not any(isinstance(m.processor, tb.LeanAttnProcessor) for m in attns)


def test_lean_attention_inside_the_multiview_processor_and_fallback():
    from diffusers.models.attention_processor import Attention, AttnProcessor2_0

    from tiger.edit.guidance.mvdream_attention import MultiViewAttnProcessor

    torch.manual_seed(0)
    attn = Attention(16, heads=2, dim_head=8)
    attn.set_processor(MultiViewAttnProcessor(2))
    h = torch.randn(4, 5, 16)
    with torch.no_grad():
        y0 = attn(h)
        assert tb.set_lean_attention(attn, True) == 1 and isinstance(attn.processor.inner, tb.LeanAttnProcessor)
        assert torch.equal(attn(h), y0)
        attn.rescale_output_factor = 2.0  # a feature it does not handle: diffusers' processor runs
        torch.testing.assert_close(attn(h), y0 / 2.0)
    tb.set_lean_attention(attn, False)
    assert type(attn.processor.inner) is AttnProcessor2_0


@pytest.fixture
def unet64(tiny_ip2p):
    """The tiny InstructPix2Pix UNet in float64 with the lean attention (a copy per test)."""
    unet = copy.deepcopy(tiny_ip2p.unet).double().eval()
    tb.set_lean_attention(unet, True)
    return unet


def _block_inputs(block, batch: int, tokens: int, seed: int):
    """float64 tokens [batch, tokens, C] and text [batch, 77, D] for one call of ``block``."""
    gen = torch.Generator().manual_seed(seed)
    h = torch.randn(batch, tokens, block.norm1.normalized_shape[0], generator=gen, dtype=torch.float64)
    return h, torch.randn(batch, 77, block.attn2.to_k.in_features, generator=gen, dtype=torch.float64)


@pytest.fixture
def fused_block(unet64):
    """The tiny UNet's first transformer block, fused, and one float64 call's inputs (h, text)."""
    block = _blocks(unet64)[0]
    tb.set_fused_transformer(block, True)
    return (block, *_block_inputs(block, 2, 9, seed=0))


def _perturb_biases(unet):
    """Give every bias a visible value (random models may start them at zero, which would hide a
    bias carried to the wrong place)."""
    gen = torch.Generator().manual_seed(3)
    with torch.no_grad():
        for m in unet.modules():
            if type(m) is torch.nn.Linear and m.bias is not None:
                m.bias.copy_(torch.randn(m.bias.shape, generator=gen, dtype=m.bias.dtype))


def test_fused_blocks_equal_diffusers_in_float64(unet64, unet_inputs):
    _perturb_biases(unet64)
    x, t, e = unet_inputs(unet64, torch.float64)
    with torch.no_grad():
        ref = unet64(x, t, encoder_hidden_states=e).sample
        n = tb.set_fused_transformer(unet64, True)
        assert n == len(_blocks(unet64)) > 0
        assert tb.set_fused_transformer(unet64, True) == n  # idempotent
        got = unet64(x, t, encoder_hidden_states=e).sample
    torch.testing.assert_close(got, ref, atol=1e-10 * float(ref.abs().max()), rtol=0)
    assert tb.set_fused_transformer(unet64, False) == 0
    assert not any("forward" in b.__dict__ or "_tiger_fused_weights" in b.__dict__ for b in _blocks(unet64))


def test_fused_block_in_bfloat16_is_as_close_to_float64_as_diffusers(unet64, unet_inputs):
    _perturb_biases(unet64)
    block = _blocks(unet64)[0]
    h, text = _block_inputs(block, 3, 16, seed=1)
    with torch.no_grad():
        ref = block(h.clone(), encoder_hidden_states=text)
        b16 = copy.deepcopy(block).bfloat16()
        theirs = b16(h.bfloat16(), encoder_hidden_states=text.bfloat16()).double()
        tb.set_fused_transformer(b16, True)
        ours = b16(h.bfloat16(), encoder_hidden_states=text.bfloat16()).double()
    err_ours, err_theirs = (float((v - ref).norm() / ref.norm()) for v in (ours, theirs))
    assert err_ours < 0.02 and err_ours <= 1.5 * err_theirs, (err_ours, err_theirs)


def _graphed_block_output(block, h: torch.Tensor, text: torch.Tensor) -> torch.Tensor:
    """``block(h, encoder_hidden_states=text)`` captured in a CUDA graph (after one call on the
    capture stream) and replayed on a fresh copy of ``h``; synchronised."""
    with torch.no_grad():
        graph, x = torch.cuda.CUDAGraph(), h.clone()
        s = torch.cuda.Stream()
        s.wait_stream(torch.cuda.current_stream())
        with torch.cuda.stream(s):
            block(h.clone(), encoder_hidden_states=text)
            with torch.cuda.graph(graph, stream=s):
                out = block(x, encoder_hidden_states=text)
        torch.cuda.current_stream().wait_stream(s)
        x.copy_(h)
        graph.replay()
        torch.cuda.synchronize()
    return out


@pytest.mark.cuda
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
@pytest.mark.parametrize("dtype", [torch.bfloat16, torch.float32])
def test_fused_block_on_cuda_is_as_close_to_float64_as_diffusers(unet64, dtype):
    """cuBLAS's in-place accumulation and the LayerNorm kernel's input bias, in a CUDA graph too."""
    _perturb_biases(unet64)
    block = _blocks(unet64)[-1]
    h, text = _block_inputs(block, 4, 64, seed=2)
    with torch.no_grad():
        ref = block(h.clone(), encoder_hidden_states=text)
        dev = copy.deepcopy(block).to("cuda", dtype)
        hd, td = h.to("cuda", dtype), text.to("cuda", dtype)
        theirs = dev(hd.clone(), encoder_hidden_states=td).double().cpu()
        assert tb.set_fused_transformer(dev, True) == 1
        ours = dev(hd.clone(), encoder_hidden_states=td).double().cpu()
    assert torch.equal(_graphed_block_output(dev, hd, td).double().cpu(), ours)
    err_ours, err_theirs = (float((v - ref).norm() / ref.norm()) for v in (ours, theirs))
    bound = 0.02 if dtype == torch.bfloat16 else 1e-5
    assert err_ours < bound and err_ours <= 1.5 * err_theirs + 1e-7, (err_ours, err_theirs)


@pytest.mark.parametrize("dtype", [torch.float32, torch.bfloat16, torch.float16, torch.float64])
def test_the_extra_geglu_column_is_one(unet64, dtype):
    """The GEGLU projection's extra pairs give exactly 1 then zeros, for any input."""
    block = copy.deepcopy(_blocks(unet64)[0]).to(dtype)
    d = tb._derive(block)
    f = block.ff.net[2].in_features
    n = torch.randn(5, block.norm3.normalized_shape[0], dtype=torch.float64).to(dtype)
    proj_weight, proj_bias, _ = tb.extra_pair_weights(block, d)
    g = geglu(F.linear(n, proj_weight, proj_bias))
    assert g.shape == (5, f + 8)
    one = 1 - 1e-15 if dtype == torch.float64 else 1.0  # erf(8/sqrt 2) is 1 in float32, not in float64
    torch.testing.assert_close(g[:, f].double(), torch.full((5,), one, dtype=torch.float64), atol=1e-15, rtol=0)
    assert bool((g[:, f + 1:] == 0).all())
    torch.testing.assert_close(g[:, :f], geglu(block.ff.net[0].proj(n)))  # the same up to summation order


def test_fused_block_writes_into_its_input_and_falls_back(fused_block):
    block, h, text = fused_block
    with torch.no_grad():
        keep = h.clone()
        out = block(h, encoder_hidden_states=text)
        assert out.data_ptr() == h.data_ptr() and not torch.equal(h, keep)  # in place
        h2 = keep.clone()
        block.train()
        ref = block(h2, encoder_hidden_states=text)  # training mode: diffusers' forward
        block.eval()
        assert torch.equal(h2, keep) and ref.data_ptr() != h2.data_ptr()
    torch.testing.assert_close(out, ref, atol=1e-12, rtol=0)
    h3 = keep.clone()
    with_grad = block(h3, encoder_hidden_states=text)  # gradients on: diffusers' forward
    assert torch.equal(h3, keep)
    torch.testing.assert_close(with_grad.detach(), ref, atol=1e-12, rtol=0)
    h4 = keep.clone()
    with torch.no_grad():  # a mask is one of the features left to diffusers: its forward runs
        block(h4, encoder_hidden_states=text, encoder_attention_mask=torch.zeros(2, 1, 77, dtype=torch.float64))
    assert torch.equal(h4, keep)


def test_fused_block_derives_again_when_a_weight_changes(fused_block):
    block, h, text = fused_block
    with torch.no_grad():
        block(h.clone(), encoder_hidden_states=text)
        block.attn1.to_out[0].bias.add_(0.5)
        block.ff.net[2].weight.mul_(1.5)
        got = block(h.clone(), encoder_hidden_states=text)
        tb.set_fused_transformer(block, False)
        ref = block(h.clone(), encoder_hidden_states=text)
    torch.testing.assert_close(got, ref, atol=1e-12, rtol=0)


def test_fused_block_follows_a_dtype_change(fused_block):
    block, h, text = fused_block
    h, text = h.float(), text.float()
    block.float()  # .to() replaces the parameters' data without an in-place version bump
    with torch.no_grad():
        keep = h.clone()
        out = block(h, encoder_hidden_states=text)
        assert out.data_ptr() == h.data_ptr()  # the fused path ran on the float32 weights
        assert block.__dict__["_tiger_fused_weights"].qkv_weight.dtype == torch.float32
        tb.set_fused_transformer(block, False)
        ref = block(keep, encoder_hidden_states=text)
    torch.testing.assert_close(out, ref, atol=1e-5, rtol=1e-5)


def _set_views(unet, views: int) -> None:
    """Set every multi-view processor of ``unet`` to attend over ``views`` rows jointly."""
    for m in unet.modules():
        if getattr(m, "processor", None) is not None and hasattr(m.processor, "num_views"):
            m.processor.num_views = views


def test_mvdream_multiview_blocks_fuse_and_equal_diffusers_in_float64(mvdream_unet64, mvdream_inputs):
    """MVDream's blocks (self-attention over each group of 4 views) run fused: the same values as
    diffusers' forward with the multi-view processor, in float64; a batch of partial view groups
    falls back to diffusers (whose processor refuses it)."""
    unet = mvdream_unet64
    _perturb_biases(unet)
    x, t, emb, cams = mvdream_inputs(unet)
    with torch.no_grad():
        ref = unet(x, t, encoder_hidden_states=emb, class_labels=cams).sample
        assert tb.set_fused_transformer(unet, True) == len(_blocks(unet)) > 0
        got = unet(x, t, encoder_hidden_states=emb, class_labels=cams).sample
        # the joint attention matters: the views attending one by one give something else
        _set_views(unet, 1)
        alone = unet(x, t, encoder_hidden_states=emb, class_labels=cams).sample
        _set_views(unet, 4)
        with pytest.raises(ValueError, match="not a multiple of num_views"):
            unet(x[:6], t[:6], encoder_hidden_states=emb[:6], class_labels=cams[:6])
    torch.testing.assert_close(got, ref, atol=1e-10 * float(ref.abs().max()), rtol=0)
    assert (alone - ref).abs().max() > 1e-3 * float(ref.abs().max())


@pytest.mark.parametrize("model", ["ip2p", "mvdream"])
def test_fused_transformers_carry_the_last_blocks_biases_through_proj_out(tiny_models, model, mvdream_inputs,
                                                                           monkeypatch):
    """With tiger's fused norms (whose transformer output takes ``out_bias``), each transformer's
    last fused block leaves its three biases to ``proj_out``'s bias (a 1x1 convolution in
    InstructPix2Pix, a linear layer in MVDream): the same values as diffusers' forward in float64,
    through the carrying path (counted), and switched off cleanly."""
    from diffusers.models.transformers.transformer_2d import Transformer2DModel

    from tiger.edit.guidance.fused_norms import fuse_group_norms
    from tiger.edit.guidance.ip2p import load_ip2p
    from tiger.edit.guidance.mvdream import load_mvdream

    if model == "ip2p":
        unet = load_ip2p(tiny_models / "instruct-pix2pix", fused_norms=False).unet
    else:
        unet = load_mvdream(tiny_models / "mvdream", fused_norms=False).unet
    unet = unet.double().eval()
    tb.set_lean_attention(unet, True)
    _perturb_biases(unet)
    with torch.no_grad():
        for tr in unet.modules():
            if type(tr) is Transformer2DModel and tr.proj_out.bias is not None:
                tr.proj_out.bias.normal_(generator=torch.Generator().manual_seed(4))
    fuse_group_norms(unet)
    transformers = [m for m in unet.modules() if type(m) is Transformer2DModel]
    if model == "ip2p":
        gen = torch.Generator().manual_seed(7)
        x = torch.randn(3, unet.config.in_channels, 8, 8, generator=gen, dtype=torch.float64)
        kwargs = dict(encoder_hidden_states=torch.randn(3, 77, unet.config.cross_attention_dim, generator=gen,
                                                        dtype=torch.float64))
        t = torch.tensor([10, 200, 900])
    else:
        x, t, emb, cams = mvdream_inputs(unet)
        kwargs = dict(encoder_hidden_states=emb, class_labels=cams)
    carried = []
    real = tb._carried_out_bias
    monkeypatch.setattr(tb, "_carried_out_bias", lambda tr, d: carried.append(tr) or real(tr, d))
    with torch.no_grad():
        ref = unet(x, t, **kwargs).sample
        assert tb.set_fused_transformer(unet, True) == len(_blocks(unet))
        assert all(m.__dict__.get(tb._CARRY) for m in transformers) and transformers
        got = unet(x, t, **kwargs).sample
        again = unet(x, t, **kwargs).sample  # the cached proj_out bias
    assert len(carried) == 2 * len(transformers)
    torch.testing.assert_close(got, ref, atol=1e-10 * float(ref.abs().max()), rtol=0)
    assert torch.equal(again, got)
    tb.set_fused_transformer(unet, False)
    assert not any(k in m.__dict__ for m in transformers for k in (tb._CARRY, tb._OUT_BIAS, "forward"))


def test_what_is_not_fused(unet64):
    mk.set_matmul_precision(unet64.float(), "fp8", emulate=True)
    assert tb.set_fused_transformer(unet64, True) == 0  # FP8 layers
    mk.set_matmul_precision(unet64, "model")
    assert tb.set_fused_transformer(unet64, True) == len(_blocks(unet64))


def test_apply_model_kernels_fuses_on_cuda_models_only(tiny_ip2p):
    unet, vae = copy.deepcopy(tiny_ip2p.unet), tiny_ip2p.vae
    assert mk.apply_model_kernels(unet, vae, mk.ModelKernels())["fused_transformer_blocks"] == 0  # CPU: auto = off
    got = mk.apply_model_kernels(unet, vae, mk.ModelKernels(fused_transformer=True))
    assert got["fused_transformer_blocks"] == len(_blocks(unet)) > 0
    assert mk.apply_model_kernels(unet, vae, mk.ModelKernels(fused_transformer=False))["fused_transformer_blocks"] == 0


def _head40_block(dtype=torch.float64):
    """A diffusers transformer block as InstructPix2Pix's 64² ones: 320 channels, 8 heads of 40."""
    from diffusers.models.attention import BasicTransformerBlock

    torch.manual_seed(11)
    block = BasicTransformerBlock(320, 8, 40, cross_attention_dim=64, activation_fn="geglu").to(dtype).eval()
    tb.set_lean_attention(block, True)
    _perturb_biases(block)
    return block


def test_head40_attention_marks_the_head_dim_40_self_attentions_only(unet64):
    block = _head40_block()
    assert tb.set_head40_attention(block, True) == 1  # attn1 (8 x 40); attn2 is a cross-attention
    assert block.attn1.__dict__.get(tb._HEAD40) and not block.attn2.__dict__.get(tb._HEAD40)
    assert tb.set_head40_attention(block, False) == 0 and tb._HEAD40 not in block.attn1.__dict__
    assert tb.set_head40_attention(unet64, True) == 0  # the tiny UNet's heads are not 40 wide


@pytest.mark.parametrize("fused", [False, True])
def test_head40_attention_on_the_cpu_is_the_same_attention(fused):
    """On the CPU the op computes the reference: the block's output equals SDPA's to rounding."""
    block = _head40_block()
    h, text = _block_inputs(block, 2, 24, seed=4)
    tb.set_fused_transformer(block, fused)
    with torch.no_grad():
        ref = block(h.clone(), encoder_hidden_states=text)
        tb.set_head40_attention(block, True)
        got = block(h.clone(), encoder_hidden_states=text)
    torch.testing.assert_close(got, ref, rtol=0, atol=1e-12 * float(ref.abs().max()))


@pytest.mark.cuda
@pytest.mark.skipif(not (torch.cuda.is_available() and torch.cuda.get_device_capability() == (9, 0)),
                    reason="needs an H100-class GPU (compute capability 9.0)")
@pytest.mark.parametrize("fused", [False, True])
def test_head40_attention_on_an_h100_is_as_close_to_float64_as_sdpa(fused):
    """bf16 block on the GPU, 2 x 1024 tokens: the Hopper kernel's output error against the
    float64 block is no larger than with cuDNN's SDPA (1.25x), eager and in a CUDA graph."""
    block = _head40_block()
    h, text = _block_inputs(block, 2, 1024, seed=5)
    with torch.no_grad():
        ref = block(h.clone(), encoder_hidden_states=text)
        dev = copy.deepcopy(block).to("cuda", torch.bfloat16)
        tb.set_fused_transformer(dev, fused)
        hd, td = h.to("cuda", torch.bfloat16), text.to("cuda", torch.bfloat16)
        theirs = dev(hd.clone(), encoder_hidden_states=td).double().cpu()
        assert tb.set_head40_attention(dev, True) == 1
        ours = dev(hd.clone(), encoder_hidden_states=td).double().cpu()
    assert torch.equal(_graphed_block_output(dev, hd, td).double().cpu(), ours)
    err_ours, err_theirs = (float((v - ref).norm() / ref.norm()) for v in (ours, theirs))
    assert err_ours < 0.02 and err_ours <= 1.25 * err_theirs, (err_ours, err_theirs)


def test_head40_attention_is_off_by_default(tiny_ip2p):
    """ModelKernels' default leaves the head-dim-40 self-attentions on SDPA (the kernel measured
    1.12x cuDNN's time on an H100, docs/BENCHMARKS.md); asking for it marks them."""
    block = _head40_block()
    got = mk.apply_model_kernels(block, copy.deepcopy(tiny_ip2p.vae), mk.ModelKernels())
    assert got["head40_attention_layers"] == 0 and tb._HEAD40 not in block.attn1.__dict__
    got = mk.apply_model_kernels(block, copy.deepcopy(tiny_ip2p.vae), mk.ModelKernels(head40_attention=True))
    assert got["head40_attention_layers"] == 1
