"""Streaming PCA equals a batch PCA; projection round-trips; the basis saves and loads."""
import pytest
import torch

from tiger.language.pca import PCABasis, StreamingPCA


def data(n=3000, d=12, seed=0):
    g = torch.Generator().manual_seed(seed)
    scales = torch.linspace(3.0, 0.1, d, dtype=torch.float64)
    rot = torch.linalg.qr(torch.randn(d, d, generator=g, dtype=torch.float64))[0]
    return (torch.randn(n, d, generator=g, dtype=torch.float64) * scales) @ rot.T + torch.arange(d)


def batch_pca(x, k):
    mean = x.mean(0)
    _, s, vh = torch.linalg.svd(x - mean, full_matrices=False)
    return mean, vh[:k].T, s[:k] ** 2 / (x.shape[0] - 1)


def same_subspace_columns(a, b):
    # columns agree up to sign
    return torch.allclose((a * b).sum(0).abs(), torch.ones(a.shape[1], dtype=a.dtype), atol=1e-6)


def test_streaming_equals_batch_pca():
    x = data()
    acc = StreamingPCA(12, 5)
    for chunk in x.split(317):
        acc.update(chunk)
    basis = acc.fit()
    mean, comps, var = batch_pca(x, 5)
    torch.testing.assert_close(basis.mean.double(), mean, atol=1e-5, rtol=1e-5)
    assert same_subspace_columns(basis.components.double(), comps)
    torch.testing.assert_close(basis.explained_variance.double(), var, rtol=1e-5, atol=1e-6)


def test_weights_count_rows_and_statistics_add_up():
    x = data(n=400)
    w = torch.randint(1, 5, (400,))
    repeated = torch.repeat_interleave(x, w, dim=0)
    a = StreamingPCA(12, 4)
    a.update(x[:150], w[:150].double())
    b = StreamingPCA(12, 4)  # another process / cached image's statistics
    b.update(x[150:], w[150:].double())
    a.add_statistics({"count": b.count, "sum": b.sum, "outer": b.outer})
    basis = a.fit()
    mean, comps, var = batch_pca(repeated, 4)
    torch.testing.assert_close(basis.mean.double(), mean, atol=1e-5, rtol=1e-5)
    assert same_subspace_columns(basis.components.double(), comps)


def test_round_trip_and_projection():
    x = data(n=500, d=8)
    full = StreamingPCA(8, 8)
    full.update(x)
    basis = full.fit()
    torch.testing.assert_close(basis.reconstruct(basis.project(x.float())).double(), x, atol=1e-4, rtol=1e-4)
    part = StreamingPCA(8, 3)
    part.update(x)
    b3 = part.fit()
    y = b3.project(x.float()).double()
    # the reconstruction is the orthogonal projection onto the affine PCA subspace
    c = b3.components.double()
    proj = (x - b3.mean.double()) @ c @ c.T + b3.mean.double()
    torch.testing.assert_close(b3.reconstruct(y.float()).double(), proj, atol=1e-4, rtol=1e-4)
    torch.testing.assert_close(c.T @ c, torch.eye(3, dtype=torch.float64), atol=1e-6, rtol=0)


def test_save_load(tmp_path):
    acc = StreamingPCA(6, 2)
    acc.update(data(n=100, d=6))
    basis = acc.fit()
    basis.save(tmp_path / "pca.pt")
    loaded = PCABasis.load(tmp_path / "pca.pt")
    assert torch.equal(loaded.components, basis.components) and loaded.fingerprint() == basis.fingerprint()
    with pytest.raises(FileNotFoundError, match="no PCA basis"):
        PCABasis.load(tmp_path / "missing.pt")


def test_errors():
    with pytest.raises(ValueError, match="n_components"):
        StreamingPCA(4, 5)
    with pytest.raises(ValueError, match="more than one"):
        StreamingPCA(4, 2).fit()
    with pytest.raises(ValueError, match="weights must be"):
        StreamingPCA(4, 2).update(torch.randn(3, 4), torch.ones(2))
