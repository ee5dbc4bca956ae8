"""tiger::fused_ssim against an SSIM written here from Wang et al. (2004) with a full 2-D window
(outer product of the 1-D taps, one conv2d; not the separable code under test), in float64:
values, the img1 gradient (vs autograd through that reference), gradcheck/opcheck, known answers,
errors; on CUDA the same against the float64 reference, every window radius, ragged tile edges."""
import math

import pytest
import torch
import torch.nn.functional as F

import tiger  # noqa: F401
from tiger.ops.ssim import fused_ssim

CUDA = torch.cuda.is_available() and tiger.ops.cuda_enabled()
C1, C2 = 0.01 ** 2, 0.03 ** 2  # Wang et al. 2004: K1 = 0.01, K2 = 0.03, L = 1


def taps_of(size, sigma):
    x = torch.arange(size, dtype=torch.float64) - (size - 1) / 2
    g = torch.exp(-x * x / (2 * sigma * sigma))
    return (g / g.sum()).tolist()


def reference_ssim(x, y, taps):
    """SSIM map with the 2-D window w ⊗ w, zero padding, float64."""
    k = torch.tensor(taps, dtype=torch.float64, device=x.device)
    w2 = torch.outer(k, k)[None, None].expand(x.shape[1], 1, -1, -1)
    pad = len(taps) // 2
    x, y = x.double(), y.double()

    def win(t):
        return F.conv2d(t, w2, padding=pad, groups=x.shape[1])
    mu1, mu2 = win(x), win(y)
    s11, s22, s12 = win(x * x) - mu1 ** 2, win(y * y) - mu2 ** 2, win(x * y) - mu1 * mu2
    return ((2 * mu1 * mu2 + C1) * (2 * s12 + C2)) / ((mu1 ** 2 + mu2 ** 2 + C1) * (s11 + s22 + C2))


def images(shape, dtype=torch.float64, device="cpu", seed=0):
    g = torch.Generator().manual_seed(seed)
    x = torch.rand(shape, generator=g, dtype=torch.float64)
    y = (x + 0.2 * torch.randn(shape, generator=g, dtype=torch.float64)).clamp(0, 1)
    return x.to(device, dtype), y.to(device, dtype)


@pytest.mark.parametrize("shape,size,sigma", [((1, 3, 20, 17), 11, 1.5), ((2, 2, 9, 13), 7, 1.2),
                                              ((1, 1, 4, 3), 11, 1.5), ((1, 2, 6, 6), 1, 1.0)])
def test_cpu_values_and_gradient_match_reference(shape, size, sigma):
    x, y = images(shape)
    taps = taps_of(size, sigma)
    xr = x.clone().requires_grad_()
    m = fused_ssim(xr, y, taps, C1, C2)
    xref = x.clone().requires_grad_()
    ref = reference_ssim(xref, y, taps)
    torch.testing.assert_close(m, ref, atol=1e-12, rtol=0)
    gm = torch.randn(shape, generator=torch.Generator().manual_seed(3), dtype=torch.float64)
    (g,) = torch.autograd.grad(m, xr, gm)
    (gref,) = torch.autograd.grad(ref, xref, gm)
    torch.testing.assert_close(g, gref, atol=1e-11, rtol=0)


def test_float32_close_to_float64_reference():
    x, y = images((1, 3, 31, 40))
    taps = taps_of(11, 1.5)
    xr = x.float().requires_grad_()
    m = fused_ssim(xr, y.float(), taps, C1, C2)
    xref = x.clone().requires_grad_()
    ref = reference_ssim(xref, y, taps)
    assert (m.double() - ref).abs().max() < 1e-5
    (g,) = torch.autograd.grad(m.mean(), xr)
    (gref,) = torch.autograd.grad(ref.mean(), xref)
    assert (g.double() - gref).abs().max() / gref.abs().max() < 1e-4


def test_gradcheck_and_opcheck():
    x, y = images((1, 2, 7, 6))
    taps = taps_of(5, 1.0)
    xr = x.requires_grad_()
    assert torch.autograd.gradcheck(lambda a: fused_ssim(a, y, taps, C1, C2), (xr,))
    torch.library.opcheck(torch.ops.tiger.fused_ssim, (xr, y, taps, C1, C2))
    _, dm = torch.ops.tiger.fused_ssim(x.detach(), y, taps, C1, C2)
    torch.library.opcheck(torch.ops.tiger.fused_ssim_backward, (torch.rand_like(x), x.detach(), y, dm, taps))


def test_known_answers():
    x, _ = images((1, 1, 15, 15))
    taps = taps_of(11, 1.5)
    torch.testing.assert_close(fused_ssim(x, x, taps, C1, C2), torch.ones_like(x), atol=1e-13, rtol=0)
    # constant images a and b: no variance, so SSIM = (2ab + C1) / (a² + b² + C1) wherever the
    # window lies inside the image (zero padding changes the means at the borders)
    a, b = 0.3, 0.7
    m = fused_ssim(torch.full((1, 1, 15, 15), a, dtype=torch.float64),
                   torch.full((1, 1, 15, 15), b, dtype=torch.float64), taps, C1, C2)
    assert math.isclose(float(m[0, 0, 7, 7]), (2 * a * b + C1) / (a * a + b * b + C1), rel_tol=1e-12)


def test_extreme_inputs_stay_finite():
    taps = taps_of(11, 1.5)
    for x, y in [(torch.zeros(1, 3, 12, 12), torch.zeros(1, 3, 12, 12)),
                 (torch.zeros(1, 3, 12, 12), torch.ones(1, 3, 12, 12)),
                 (torch.full((1, 3, 12, 12), 1e3), torch.full((1, 3, 12, 12), -1e3))]:
        xr = x.requires_grad_()
        m = fused_ssim(xr, y, taps, C1, C2)
        (g,) = torch.autograd.grad(m.sum(), xr)
        assert torch.isfinite(m).all() and torch.isfinite(g).all()


def test_errors_name_the_problem():
    x = torch.zeros(1, 3, 8, 8)
    taps = taps_of(11, 1.5)
    with pytest.raises(RuntimeError, match="img2 must have img1's shape"):
        fused_ssim(x, torch.zeros(1, 3, 8, 7), taps, C1, C2)
    with pytest.raises(RuntimeError, match=r"img1 must be \[B, C, H, W\]"):
        fused_ssim(torch.zeros(3, 8, 8), torch.zeros(3, 8, 8), taps, C1, C2)
    with pytest.raises(RuntimeError, match="odd number"):
        fused_ssim(x, x, [0.5, 0.5], C1, C2)
    with pytest.raises(RuntimeError, match="odd number"):
        fused_ssim(x, x, taps_of(13, 2.0), C1, C2)
    with pytest.raises(RuntimeError, match="float32 or float64"):
        fused_ssim(x.half(), x.half(), taps, C1, C2)
    with pytest.raises(RuntimeError, match="img2 has dtype"):
        fused_ssim(x, x.double(), taps, C1, C2)
    y = torch.zeros(1, 3, 8, 8, requires_grad=True)
    with pytest.raises(RuntimeError, match="no gradient for img2"):
        fused_ssim(x.requires_grad_(), y, taps, C1, C2).sum().backward()


@pytest.mark.skipif(not CUDA, reason="needs CUDA")
@pytest.mark.parametrize("size", [3, 5, 7, 9, 11, 1])
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_cuda_matches_reference(size, dtype):
    shape = (2, 3, 37, 70)  # ragged against the 32 x 16 (8 in float64) tiles
    x, y = images(shape)
    taps = taps_of(size, 1.5)
    xr = x.to("cuda", dtype).requires_grad_()
    m = fused_ssim(xr, y.to("cuda", dtype), taps, C1, C2)
    xref = x.clone().requires_grad_()
    ref = reference_ssim(xref, y, taps)
    gm = torch.randn(shape, generator=torch.Generator().manual_seed(5), dtype=torch.float64)
    (g,) = torch.autograd.grad(m, xr, gm.to("cuda", dtype))
    (gref,) = torch.autograd.grad(ref, xref, gm)
    # float32: a 1-tap window is SSIM of single pixels, whose variances e11 - mu1² cancel exactly
    # in exact arithmetic but not in float32 (6.5e-5 seen on the H100)
    tol = 1e-12 if dtype == torch.float64 else (2e-5 if size > 1 else 2e-4)
    assert (m.double().cpu() - ref).abs().max() < tol
    assert (g.double().cpu() - gref).abs().max() / gref.abs().max() < (1e-11 if dtype == torch.float64 else 1e-4)
    if dtype == torch.float64:  # and the CPU kernel gives the same numbers
        mc = fused_ssim(x, y, taps, C1, C2)
        torch.testing.assert_close(m.cpu(), mc, atol=1e-12, rtol=0)  # fused multiply-adds differ


@pytest.mark.skipif(not CUDA, reason="needs CUDA")
def test_cuda_noncontiguous_and_tiny_inputs():
    x, y = images((1, 3, 40, 50))
    xc, yc = x.cuda().permute(0, 1, 3, 2), y.cuda().permute(0, 1, 3, 2)  # strided views
    taps = taps_of(11, 1.5)
    torch.testing.assert_close(fused_ssim(xc, yc, taps, C1, C2).cpu(),
                               reference_ssim(x.permute(0, 1, 3, 2), y.permute(0, 1, 3, 2), taps), atol=1e-12, rtol=0)
    x, y = images((1, 1, 2, 3))
    torch.testing.assert_close(fused_ssim(x.cuda(), y.cuda(), taps, C1, C2).cpu(), reference_ssim(x, y, taps),
                               atol=1e-12, rtol=0)
