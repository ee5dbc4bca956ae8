"""The one Gaussian blur: every method and padding against scipy's 1-D correlation."""
from __future__ import annotations

import numpy as np
import pytest
import torch
from scipy.ndimage import correlate1d

from tiger.utils.filters import gaussian_blur


def _scipy_blur(x: np.ndarray, size: int, sigma: float, mode: str) -> np.ndarray:
    r = np.arange(size) - (size - 1) / 2
    w = np.exp(-r * r / (2 * sigma * sigma))
    w /= w.sum()
    # torch's "reflect" (no edge repeat) is scipy's "mirror"; zero padding is "constant".
    y = correlate1d(x, w, axis=-1, mode=mode, cval=0.0)
    return correlate1d(y, w, axis=-2, mode=mode, cval=0.0)


@pytest.mark.parametrize("padding,mode", [("zeros", "constant"), ("reflect", "mirror")])
def test_blur_matches_scipy_for_every_method(padding, mode):
    x = torch.rand(2, 3, 13, 17, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    want = torch.from_numpy(_scipy_blur(x.numpy(), 5, 1.0, mode))
    methods = ["conv", "depthwise", "shift", "auto"] + (["matmul"] if padding == "zeros" else [])
    for m in methods:
        torch.testing.assert_close(gaussian_blur(x, 5, 1.0, method=m, padding=padding), want,
                                   rtol=0, atol=1e-14, msg=m)


@pytest.mark.parametrize("method", ["conv", "depthwise", "matmul", "shift"])
def test_zero_padded_blur_backward_is_its_adjoint(method):
    """The zero-padded blur's backward is the blur itself (a symmetric map): gradcheck against
    finite differences, and the same gradient as autograd through scipy's transpose written as
    an explicit [HW, HW] matrix."""
    x = torch.rand(1, 2, 9, 7, dtype=torch.float64, generator=torch.Generator().manual_seed(1),
                   requires_grad=True)
    assert torch.autograd.gradcheck(lambda t: gaussian_blur(t, 5, 1.0, method=method), (x,))
    eye = np.eye(9 * 7).reshape(9 * 7, 9, 7)
    M = _scipy_blur(eye, 5, 1.0, "constant").reshape(9 * 7, 9 * 7)   # row k: blur of basis k
    v = torch.rand(1, 2, 9, 7, dtype=torch.float64, generator=torch.Generator().manual_seed(2))
    (gaussian_blur(x, 5, 1.0, method=method) * v).sum().backward()
    want = (torch.from_numpy(M) @ v.reshape(2, -1).T).T.reshape(1, 2, 9, 7)
    torch.testing.assert_close(x.grad, want, rtol=0, atol=1e-14)


def test_auto_is_the_depthwise_filter(monkeypatch):
    """"auto" runs the depthwise convolution (one group per channel; fastest on the CPU and on
    the H100 in benchmarks/recon_ssim.py), with and without gradients."""
    import tiger.utils.filters as filters

    groups = []
    real = filters.F.conv2d

    def spy(*args, **kwargs):
        groups.append(kwargs.get("groups", 1))
        return real(*args, **kwargs)

    monkeypatch.setattr(filters.F, "conv2d", spy)
    x = torch.rand(2, 15, 30, 41, dtype=torch.float64, generator=torch.Generator().manual_seed(3))
    gaussian_blur(x)
    gaussian_blur(x.clone().requires_grad_()).sum().backward()
    assert groups == [15] * 6  # two 1-D passes per forward (2) and in the self-adjoint backward


def test_blur_errors_name_the_problem():
    x = torch.zeros(1, 1, 8, 8)
    with pytest.raises(ValueError, match="padding must be"):
        gaussian_blur(x, padding="wrap")
    with pytest.raises(ValueError, match="zero padding only"):
        gaussian_blur(x, method="matmul", padding="reflect")
    with pytest.raises(ValueError, match="method must be"):
        gaussian_blur(x, method="fft")
    with pytest.raises(ValueError, match=r"\[B, C, H, W\]"):
        gaussian_blur(torch.zeros(8, 8))


def test_dilate_matches_scipy_binary_dilation():
    """Disk and square dilation equal scipy.ndimage.binary_dilation with the same structuring
    element (an independent implementation), on random masks with a leading batch dimension."""
    import numpy as np
    import pytest
    from scipy import ndimage

    from tiger.utils.filters import dilate

    g = torch.Generator().manual_seed(3)
    masks = torch.rand(3, 23, 17, generator=g) > 0.97
    for radius in (0, 1, 2, 4):
        r = np.arange(-radius, radius + 1)
        disk = (r[:, None] ** 2 + r[None, :] ** 2) <= radius * radius
        square = np.ones((2 * radius + 1, 2 * radius + 1), bool)
        for shape, se in (("disk", disk), ("square", square)):
            got = dilate(masks, radius, shape)
            want = np.stack([ndimage.binary_dilation(m.numpy(), structure=se) for m in masks])
            assert np.array_equal(got.numpy(), want), (shape, radius)
    one = torch.zeros(9, 9, dtype=torch.bool)
    one[4, 4] = True
    assert int(dilate(one, 2, "disk").sum()) == 13 and int(dilate(one, 2, "square").sum()) == 25
    with pytest.raises(ValueError, match="radius"):
        dilate(one, -1)
    with pytest.raises(ValueError, match="shape"):
        dilate(one, 1, "diamond")
