"""tiger.utils.video: browser-playable containers/codecs (read from the bytes) and round trips."""
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


def _decode(path):
    cv2 = pytest.importorskip("cv2")
    cap = cv2.VideoCapture(str(path))
    decoded = []
    while True:
        ok, bgr = cap.read()
        if not ok:
            break
        decoded.append(bgr[:, :, ::-1].astype(np.float64) / 255)
    return decoded


def browser_codec(path) -> str:
    """The container/codec pair of a video file read from its bytes (independent of the writer):
    'mp4/h264', 'mp4/mpeg4-part2', 'webm/vp9', 'webm/vp8', 'gif' or 'unknown'."""
    data = path.read_bytes()
    if data[4:8] == b"ftyp":
        return "mp4/h264" if b"avc1" in data and b"avcC" in data else (
            "mp4/mpeg4-part2" if b"mp4v" in data else "mp4/unknown")
    if data[:4] == bytes.fromhex("1a45dfa3"):  # EBML magic; Matroska/WebM CodecID element strings
        if b"webm" not in data[:64]:
            return "matroska"
        return "webm/vp9" if b"V_VP9" in data else ("webm/vp8" if b"V_VP8" in data else "webm/unknown")
    if data[:6] in (b"GIF87a", b"GIF89a"):
        return "gif"
    return "unknown"


def test_auto_writes_a_codec_browsers_play(tmp_path):
    path = write_video(frames(), tmp_path / "clip", fps=10)
    assert browser_codec(path) in ("mp4/h264", "webm/vp9", "webm/vp8", "gif"), browser_codec(path)
    assert path.suffix == {"mp4": ".mp4", "webm": ".webm", "gif": ".gif"}[browser_codec(path).split("/")[0]]
    assert [p.name for p in tmp_path.iterdir()] == [path.name]  # no temporary left behind


def test_mp4_is_h264_or_refused(tmp_path):
    try:
        path = write_video(frames(), tmp_path / "clip", fps=10, kind="mp4")
    except RuntimeError as exc:  # no H.264 encoder here: named, never an MPEG-4 Part 2 file
        assert "H.264" in str(exc) and not list(tmp_path.iterdir())
        return
    assert browser_codec(path) == "mp4/h264"
    decoded = _decode(path)
    assert len(decoded) == N
    for got, want in zip(decoded, frames()):
        assert got.shape == (H, W, 3)
        assert np.abs(got.mean(axis=(0, 1)) - want[0, 0].numpy()).max() < 6 / 255


def test_webm_decodes_to_the_frames(tmp_path):
    try:
        path = write_video(frames(), tmp_path / "clip", fps=10, kind="webm")
    except RuntimeError as exc:
        pytest.skip(f"no VP9/VP8 encoder here: {exc}")
    assert path == tmp_path / "clip.webm" and browser_codec(path) in ("webm/vp9", "webm/vp8")
    decoded = _decode(path)
    assert len(decoded) == N
    for got, want in zip(decoded, frames()):
        assert got.shape == (H, W, 3)
        # lossy codec: flat colours come back within a few levels
        assert np.abs(got.mean(axis=(0, 1)) - want[0, 0].numpy()).max() < 8 / 255


def test_odd_sizes_are_cropped_to_even_for_video(tmp_path):
    odd = [f[:47, :63] for f in frames()]
    path = write_video(odd, tmp_path / "clip", fps=10)
    if path.suffix != ".gif":
        decoded = _decode(path)
        assert decoded and decoded[0].shape == (46, 62, 3)


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


def test_mp4_without_imageio_ffmpeg_names_what_to_install(tmp_path, monkeypatch):
    """With no H.264 encoder in OpenCV and no imageio-ffmpeg, MP4 is refused in one line that names
    the missing package (imageio would otherwise try another plugin and fail with its own message),
    and nothing is left behind."""
    import importlib.util

    import tiger.utils.video as video

    real = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec", lambda name, *a: None if name == "imageio_ffmpeg" else real(name, *a))
    monkeypatch.setattr(video, "_ENCODERS", {**video._ENCODERS, "mp4": (video._imageio_h264,)})
    with pytest.raises(RuntimeError) as err:
        write_video(frames(), tmp_path / "clip", fps=10, kind="mp4")
    msg = str(err.value)
    assert "imageio-ffmpeg is not installed" in msg and "\n" not in msg
    assert not list(tmp_path.iterdir())


def test_webm_tries_vp8_before_vp9():
    """The default order, from its measurement (docs/BENCHMARKS.md, "`tiger edit` end to end"): for
    the turntable OpenCV's VP8 took 0.54 s against VP9's 3.61 s at the same PSNR (37.47 / 37.52 dB)."""
    import tiger.utils.video as video

    assert [w.__name__ for w in video._ENCODERS["webm"]] == ["opencv_VP80", "opencv_VP90"]


def test_check_video_kind_refuses_what_cannot_be_written(monkeypatch):
    """An explicit container without a working encoder is refused up front with write_video's
    message (encoders tried, what to install); auto / gif / none always pass."""
    from tiger.utils import video

    def broken(arrays, tmp, fps):
        raise RuntimeError("no encoder in this build")

    monkeypatch.setitem(video._ENCODERS, "mp4", (broken,))
    with pytest.raises(RuntimeError, match=r"cannot write MP4 \(broken: no encoder in this build\); install imageio"):
        video.check_video_kind("mp4")
    for kind in ("auto", "gif", "none"):
        video.check_video_kind(kind)
    with pytest.raises(ValueError, match="kind must be one of"):
        video.check_video_kind("avi")
