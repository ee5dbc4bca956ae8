"""tiger.utils.video: MP4 and GIF round trips, decoded with independent readers."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from tiger.utils.video import write_video

W, H, N = 64, 48, 6


def frames() -> list[torch.Tensor]:
    """N frames of flat, distinct colours [H, W, 3] in [0, 1]."""
    out = []
    for k in range(N):
        rgb = torch.tensor([k / (N - 1), 1 - k / (N - 1), 0.5 if k % 2 else 0.1])
        out.append(rgb.expand(H, W, 3).clone())
    return out


def test_mp4_decodes_to_the_frames(tmp_path):
    cv2 = pytest.importorskip("cv2")
    path = write_video(frames(), tmp_path / "clip", fps=10, kind="mp4")
    assert path == tmp_path / "clip.mp4" and path.stat().st_size > 0
    assert [p.name for p in tmp_path.iterdir()] == ["clip.mp4"]  # no temporary left behind
    cap = cv2.VideoCapture(str(path))
    decoded = []
    while True:
        ok, bgr = cap.read()
        if not ok:
            break
        decoded.append(bgr[:, :, ::-1].astype(np.float64) / 255)
    assert len(decoded) == N
    for got, want in zip(decoded, frames()):
        assert got.shape == (H, W, 3)
        # lossy codec: flat colours come back within a few levels
        assert np.abs(got.mean(axis=(0, 1)) - want[0, 0].numpy()).max() < 6 / 255


def test_gif_and_none(tmp_path):
    from PIL import Image

    path = write_video(frames(), tmp_path / "clip", fps=10, kind="gif")
    assert path.suffix == ".gif"
    with Image.open(path) as gif:
        assert gif.n_frames == N and gif.size == (W, H)
        gif.seek(3)
        rgb = np.asarray(gif.convert("RGB"), dtype=np.float64) / 255
    assert np.abs(rgb.mean(axis=(0, 1)) - frames()[3][0, 0].numpy()).max() < 3 / 255
    assert write_video(frames(), tmp_path / "x", kind="none") is None


def test_bad_input_names_the_problem(tmp_path):
    with pytest.raises(ValueError, match="kind must be one of"):
        write_video(frames(), tmp_path / "v", kind="avi")
    with pytest.raises(ValueError, match="empty"):
        write_video([], tmp_path / "v")
    with pytest.raises(ValueError, match=r"frame 1 has shape \[10, 10, 3\]"):
        write_video([torch.zeros(8, 8, 3), torch.zeros(10, 10, 3)], tmp_path / "v")
    with pytest.raises(ValueError, match=r"\[H, W, 3\]"):
        write_video([torch.zeros(8, 8)], tmp_path / "v")
    with pytest.raises(ValueError, match="fps"):
        write_video(frames(), tmp_path / "v", fps=0)
