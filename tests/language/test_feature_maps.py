"""ResidentMaps brings every view's map into memory once: in camera order, bit for bit."""
import pytest
import torch

from tiger.language.feature_maps import ResidentMaps


def _maps(count, device="cpu"):
    g = torch.Generator().manual_seed(0)
    return [(torch.randn(5 + k, 7, 3, generator=g).half().to(device), (torch.rand(5 + k, 7, generator=g) > 0.3).to(device))
            for k in range(count)]


def test_cpu_maps_are_kept_as_read():
    maps = _maps(4)
    resident = ResidentMaps(lambda i: maps[i], 4, None, torch.device("cpu"))
    for i, (f, v) in enumerate(maps):
        view = resident.get(i)
        assert view.features is f and view.valid is v and view.n_valid == int(v.sum())


@pytest.mark.cuda
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
@pytest.mark.parametrize("placement", ["device", "host"])
def test_cuda_maps_equal_the_source_maps(tmp_path, placement):
    """Memory-mapped files read on threads, through pinned copies: the same bits, in order."""
    maps = _maps(5)
    for i, (f, v) in enumerate(maps):
        torch.save({"features": f, "valid": v}, tmp_path / f"{i}.pt")
    load = lambda i: torch.load(tmp_path / f"{i}.pt", mmap=True, weights_only=True)  # noqa: E731
    resident = ResidentMaps(load, 5, None, torch.device("cuda"), placement)
    assert resident.on_device == (placement == "device")
    for i, (f, v) in enumerate(maps):
        if placement == "host":
            resident.prefetch([i])
        view = resident.get(i)
        assert view.features.is_cuda and torch.equal(view.features.cpu(), f)
        assert torch.equal(view.valid.cpu(), v) and view.n_valid == int(v.sum())
