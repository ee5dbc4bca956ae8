"""Inpainters: the LaMa TorchScript loader (padding, cropping, pasting; file errors) and OpenCV Telea."""
import numpy as np
import pytest
import torch

from tiger.delete.inpaint import LamaInpainter, OpenCVInpainter, make_inpainter
from tiger.models.paths import ENV_VAR, ModelNotFoundError


class _FakeLama(torch.nn.Module):
    """Same signature as big-lama; its output reveals the padded input it was given: a vertical
    and horizontal flip of the image, darkened where the mask is set. It fails unless H and W
    are multiples of 8 and the mask is exactly {0, 1}."""

    def forward(self, image: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
        if image.shape[2] % 8 != 0 or image.shape[3] % 8 != 0:
            raise RuntimeError("not padded to a multiple of 8")
        if not bool(((mask == 0) | (mask == 1)).all()):
            raise RuntimeError("mask is not binary")
        return image.flip(2).flip(3) * (1.0 - 0.5 * mask.flip(2).flip(3))


@pytest.fixture
def lama_file(tmp_path):
    path = tmp_path / "big-lama.pt"
    torch.jit.save(torch.jit.script(_FakeLama()), str(path))
    return path


@pytest.mark.parametrize("h,w", [(13, 21), (16, 8), (5, 3)])
def test_lama_pads_crops_and_pastes_exactly(lama_file, h, w):
    g = torch.Generator().manual_seed(0)
    img = torch.rand(2, 3, h, w, generator=g, dtype=torch.float64)
    mask = torch.rand(2, 1, h, w, generator=g) > 0.6
    out = LamaInpainter.load(lama_file, batch=2)(img, mask.float() * 0.7)  # any nonzero = fill
    # numpy reference: symmetric padding to multiples of 8, the fake net, crop, paste
    ph, pw = (-h) % 8, (-w) % 8
    pad = ((0, 0), (0, 0), (0, ph), (0, pw))
    pi = np.pad(img.float().numpy(), pad, mode="symmetric")
    pm = np.pad(mask.float().numpy(), pad, mode="symmetric")
    net = (pi[:, :, ::-1, ::-1] * (1.0 - 0.5 * pm[:, :, ::-1, ::-1]))[:, :, :h, :w]
    ref = np.where(mask.numpy(), np.clip(net, 0, 1), img.numpy())
    assert out.shape == img.shape and out.dtype == img.dtype
    assert np.array_equal(out.numpy(), ref.astype(np.float64))
    assert torch.equal(out[~mask.expand_as(img)], img[~mask.expand_as(img)])  # outside: untouched


def test_lama_found_through_registry(lama_file, monkeypatch):
    root = lama_file.parent / "models"
    (root / "lama").mkdir(parents=True)
    lama_file.rename(root / "lama" / "big-lama.pt")
    monkeypatch.setenv(ENV_VAR, str(root))
    inp = make_inpainter("lama")
    assert isinstance(inp, LamaInpainter) and inp.path == root / "lama" / "big-lama.pt"


def test_lama_missing_and_corrupt_files(tmp_path, monkeypatch):
    monkeypatch.setenv(ENV_VAR, str(tmp_path))
    with pytest.raises(ModelNotFoundError, match="big-lama.pt"):
        LamaInpainter.load()
    bad = tmp_path / "big-lama.pt"
    bad.write_bytes(b"this is not a torchscript archive")
    with pytest.raises(ValueError, match="big-lama.pt is not a TorchScript module"):
        LamaInpainter.load(bad)


def test_lama_wrong_output_shape_is_named(tmp_path):
    class Half(torch.nn.Module):
        def forward(self, image: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
            return image[:, :, ::2]

    path = tmp_path / "big-lama.pt"
    torch.jit.save(torch.jit.script(Half()), str(path))
    with pytest.raises(ValueError, match="network returned"):
        LamaInpainter.load(path)(torch.rand(1, 3, 8, 8), torch.ones(1, 1, 8, 8))


def test_opencv_fills_smooth_image_inside_mask_only():
    # a linear ramp: Telea's fill of a small hole must be close to the ramp itself
    h, w = 40, 50
    yy, xx = torch.meshgrid(torch.linspace(0, 1, h), torch.linspace(0, 1, w), indexing="ij")
    img = torch.stack([xx, yy, 0.5 * (xx + yy)])[None]
    mask = torch.zeros(1, 1, h, w, dtype=torch.bool)
    mask[..., 15:25, 20:30] = True
    holed = img.clone()
    holed[mask.expand_as(img)] = 0.0
    out = OpenCVInpainter()(holed, mask)
    assert torch.equal(out[~mask.expand_as(img)], holed[~mask.expand_as(img)])
    err = (out - img)[mask.expand_as(img)].abs()
    assert float(err.max()) < 0.08 and float(err.mean()) < 0.03, (err.max(), err.mean())
    # the depth path: a single float channel far from [0, 1] (OpenCV's float inpainting is not
    # scale-invariant; the channel is rescaled inside)
    depth = (3.0 + 2.0 * xx).numpy()[..., None]
    filled = OpenCVInpainter().fill_channels(depth, mask[0, 0].numpy())
    assert abs(filled - depth)[mask[0, 0].numpy()].max() < 0.2


def test_inpainter_input_errors():
    inp = OpenCVInpainter()
    with pytest.raises(ValueError, match="images must be"):
        inp(torch.rand(3, 8, 8), torch.ones(1, 8, 8))
    with pytest.raises(ValueError, match="masks must be"):
        inp(torch.rand(1, 3, 8, 8), torch.ones(1, 8, 8))
    with pytest.raises(ValueError, match="unknown inpainter"):
        make_inpainter("sd")
