"""The one PCA: directions and variances against numpy's SVD; weights count rows; the sign rule."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from tiger.utils.pca import fit_pca, moments, principal_axes


def test_fit_pca_matches_numpy_svd():
    g = torch.Generator().manual_seed(0)
    x = torch.randn(500, 6, generator=g, dtype=torch.float64) @ torch.diag(torch.tensor([5.0, 3, 2, 1, .5, .1],
                                                                                       dtype=torch.float64))
    x = x + torch.tensor([1.0, -2, 3, 0, 0, 7], dtype=torch.float64)
    mean, comps, var = fit_pca(x, 3)
    xn = x.numpy()
    xc = xn - xn.mean(0)
    _, s, vt = np.linalg.svd(xc, full_matrices=False)
    np.testing.assert_allclose(mean.numpy(), xn.mean(0), rtol=0, atol=1e-12)
    np.testing.assert_allclose(var.numpy(), s[:3] ** 2 / (len(xn) - 1), rtol=1e-10)
    # same directions up to sign, and the sign rule: each column's largest entry is positive
    np.testing.assert_allclose(np.abs(comps.numpy().T @ vt[:3].T), np.eye(3), atol=1e-10)
    big = comps.gather(0, comps.abs().argmax(0, keepdim=True))
    assert bool((big > 0).all())


def test_weights_count_rows():
    g = torch.Generator().manual_seed(1)
    x = torch.randn(30, 4, generator=g, dtype=torch.float64)
    w = torch.randint(1, 4, (30,), generator=g)
    a = fit_pca(x, 2, w.double())
    b = fit_pca(x.repeat_interleave(w, 0), 2)
    for u, v in zip(a, b):
        torch.testing.assert_close(u, v, rtol=1e-10, atol=1e-12)


def test_bad_inputs():
    with pytest.raises(ValueError, match="0 < k <= D"):
        fit_pca(torch.randn(10, 3), 4)
    with pytest.raises(ValueError, match="more than one"):
        m = moments(torch.randn(1, 3))
        principal_axes(m["count"], m["sum"], m["outer"], 2)
    with pytest.raises(ValueError, match=r"weights must be \[N\]"):
        moments(torch.randn(5, 3), torch.ones(4))


def test_principal_axes_same_bits_for_any_thread_count():
    """The basis a single process fits equals the one a torchrun rank (one thread) fits, bit for bit."""
    g = torch.Generator().manual_seed(0)
    m = moments(torch.randn(3000, 256, generator=g, dtype=torch.float64) @ torch.randn(256, 256, generator=g,
                                                                                     dtype=torch.float64))
    threads = torch.get_num_threads()
    try:
        torch.set_num_threads(1)
        one = principal_axes(m["count"], m["sum"], m["outer"], 32)
        torch.set_num_threads(max(2, threads))
        many = principal_axes(m["count"], m["sum"], m["outer"], 32)
    finally:
        torch.set_num_threads(threads)
    assert all(torch.equal(a, b) for a, b in zip(one, many))
    assert torch.get_num_threads() == threads
