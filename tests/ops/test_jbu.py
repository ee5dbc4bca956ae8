"""tiger::adaptive_conv against an unfold reference, and the JBU stack (FeatUp layout) built on it."""
import pytest
import torch
import torch.nn.functional as F

import tiger  # noqa: F401
from tiger.language.featup import JBUStack
from tiger.ops.jbu import adaptive_conv

CUDA = torch.cuda.is_available() and tiger.ops.cuda_enabled()


def reference(inp, filters):
    b, c, hp, wp = inp.shape
    _, h, w, k, _ = filters.shape
    cols = F.unfold(inp, k).reshape(b, c, k * k, h, w)  # patch order (i, j) row-major
    return torch.einsum("bcphw,bhwp->bchw", cols, filters.reshape(b, h, w, k * k))


def make(b=2, c=3, h=5, w=7, k=3, dtype=torch.float64, seed=0):
    g = torch.Generator().manual_seed(seed)
    inp = torch.randn(b, c, h + k - 1, w + k - 1, generator=g, dtype=dtype)
    filt = torch.randn(b, h, w, k, k, generator=g, dtype=dtype)
    return inp, filt


@pytest.mark.parametrize("k", [1, 3, 7])
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_forward_matches_unfold(k, dtype):
    inp, filt = make(k=k, dtype=dtype)
    tol = 1e-12 if dtype == torch.float64 else 1e-5
    torch.testing.assert_close(adaptive_conv(inp, filt), reference(inp, filt), atol=tol, rtol=tol)


def test_gradients():
    inp, filt = make(b=1, c=2, h=4, w=3, k=3)
    inp.requires_grad_()
    filt.requires_grad_()
    assert torch.autograd.gradcheck(adaptive_conv, (inp, filt))
    g = torch.randn(1, 2, 4, 3, dtype=torch.float64)
    gi, gf = torch.autograd.grad((adaptive_conv(inp, filt) * g).sum(), (inp, filt))
    ri, rf = torch.autograd.grad((reference(inp, filt) * g).sum(), (inp, filt))
    torch.testing.assert_close(gi, ri)
    torch.testing.assert_close(gf, rf)
    torch.library.opcheck(torch.ops.tiger.adaptive_conv, (inp.detach(), filt.detach()))


def test_bad_shapes_name_the_tensor():
    inp, filt = make()
    with pytest.raises(RuntimeError, match="input must be \\[B, C, H \\+ K - 1"):
        adaptive_conv(inp[..., 1:], filt)
    with pytest.raises(RuntimeError, match="filters must be \\[B, H, W, K, K\\]"):
        adaptive_conv(inp, filt[..., :2])
    with pytest.raises(RuntimeError, match="must have the dtype of input"):
        adaptive_conv(inp, filt.float())


def jbu_reference_forward(stack, source, guidance):
    """FeatUp's JBUStack forward with the adaptive convolution done by unfold (independent path)."""
    def stage(up, src, guide):
        b, _, gh, gw = guide.shape
        kernel = up.range_kernel(guide) * up.spatial_kernel()
        kernel = kernel / kernel.sum(1, keepdim=True).clamp(1e-7)
        kernel = kernel + 0.1 * up.fixup_proj(torch.cat([kernel, guide], 1))
        kernel = kernel.permute(0, 2, 3, 1).reshape(b, gh, gw, up.diameter, up.diameter)
        hr = F.interpolate(src, (gh, gw), mode="bicubic", align_corners=False)
        return reference(F.pad(hr, [up.radius] * 4, mode="reflect"), kernel)

    for up in (stack.up1, stack.up2, stack.up3, stack.up4):
        h, w = source.shape[-2:]
        source = stage(up, source, F.adaptive_avg_pool2d(guidance, (2 * h, 2 * w)))
    return stack.fixup_proj(source) * 0.1 + source


def test_jbu_stack_forward_and_checkpoint(tmp_path):
    torch.manual_seed(0)
    stack = JBUStack(6).double().eval()
    src = torch.randn(1, 6, 3, 4, dtype=torch.float64)
    guide = torch.randn(1, 3, 48, 64, dtype=torch.float64)
    out = stack(src, guide)
    assert out.shape == (1, 6, 48, 64)
    torch.testing.assert_close(out, jbu_reference_forward(stack, src, guide))
    # FeatUp's Lightning checkpoint layout: state_dict with 'upsampler.' keys, plus other modules
    state = {f"upsampler.{k}": v.float() for k, v in stack.state_dict().items()}
    state["downsampler.w"] = torch.zeros(3)
    torch.save({"state_dict": state, "epoch": 3}, tmp_path / "maskclip_jbu_stack_cocostuff.ckpt")
    loaded = JBUStack.from_checkpoint(tmp_path / "maskclip_jbu_stack_cocostuff.ckpt").double()
    torch.testing.assert_close(loaded(src, guide), out)


@pytest.mark.cuda
@pytest.mark.skipif(not CUDA, reason="needs CUDA and tiger's CUDA kernels")
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_cuda_matches_cpu(dtype):
    inp, filt = make(b=2, c=33, h=37, w=29, k=7, dtype=dtype)
    a = inp.clone().requires_grad_()
    f = filt.clone().requires_grad_()
    ac = inp.cuda().requires_grad_()
    fc = filt.cuda().requires_grad_()
    tol = 1e-10 if dtype == torch.float64 else 1e-4
    out, outc = adaptive_conv(a, f), adaptive_conv(ac, fc)
    torch.testing.assert_close(outc.cpu(), out, atol=tol, rtol=tol)
    g = torch.randn_like(out)
    (out * g).sum().backward()
    (outc * g.cuda()).sum().backward()
    torch.testing.assert_close(ac.grad.cpu(), a.grad, atol=tol, rtol=tol)
    torch.testing.assert_close(fc.grad.cpu(), f.grad, atol=tol * 10, rtol=tol * 10)
    torch.library.opcheck(torch.ops.tiger.adaptive_conv, (inp.cuda(), filt.cuda()))
