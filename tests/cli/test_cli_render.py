"""tiger render of a captured scene: views along the capture's cameras (cameras.json beside the
PLY), --views / --downscale, pictures named after the source images."""
from __future__ import annotations

import numpy as np
import pytest
import torch
from PIL import Image

from tiger.cli.main import main
from tiger.scene.cameras_json import read_cameras_json, write_cameras_json
from tiger.scene.dataset import load_dataset

from ..render.devices import DEVICES
from .datasets import tabletop_dataset


@pytest.fixture(scope="module")
def captured(tmp_path_factory):
    """The scene the dataset was rendered from, saved as a PLY with the capture's cameras.json."""
    from tiger.demo import tabletop_scene

    root = tmp_path_factory.mktemp("render")
    data = tabletop_dataset(root / "data")
    scene = tabletop_scene(density=0.15).scene
    scene.save_ply(root / "scene" / "scene.ply")
    write_cameras_json(root / "scene" / "cameras.json", load_dataset(data).cameras)
    return root / "scene" / "scene.ply", data


def _png(path):
    return torch.from_numpy(np.array(Image.open(path).convert("RGB"))).float() / 255


def test_default_views_follow_the_capture_and_reproduce_its_pictures(captured, tmp_path, capsys):
    ply, data = captured
    out = tmp_path / "r"
    assert main(["render", str(ply), "--what", "color", "alpha", "--out", str(out), "--device", "cpu"]) == 0
    assert "6 of 6 capture path in" in capsys.readouterr().out
    names = sorted(p.name for p in out.glob("*_color.png"))
    assert names == [f"{i:03d}_color.png" for i in range(6)]  # the source names, no extension
    for i in (0, 3):
        ours, ref = _png(out / f"{i:03d}_color.png"), _png(data / "images" / f"{i:03d}.png")
        alpha = torch.from_numpy(np.array(Image.open(out / f"{i:03d}_alpha.png"))).float() / 255
        covered = alpha >= 0.999  # the dataset has a white background, the render a black one
        assert covered.float().mean() > 0.05
        assert float((ours - ref)[covered].abs().mean()) < 0.01


def test_views_and_downscale(captured, tmp_path, capsys):
    ply, _ = captured
    out = tmp_path / "r"
    assert main(["render", str(ply), "--views", "2", "--downscale", "2", "--what", "color", "--out", str(out),
                 "--device", "cpu"]) == 0
    names = sorted(p.name for p in out.glob("*.png"))
    assert names == ["000_color.png", "005_color.png"]  # the two ends of the path
    assert Image.open(out / "000_color.png").size == (32, 24)
    out2 = tmp_path / "r2"
    assert main(["render", str(ply), "--views", "1,4", "--what", "color", "--out", str(out2)]) == 0
    assert sorted(p.name for p in out2.glob("*.png")) == ["001_color.png", "004_color.png"]
    assert main(["render", str(ply), "--views", "9,", "--out", str(tmp_path / "r3")]) == 2
    assert "view indices [9] are out of range: there are 6 cameras" in capsys.readouterr().err
    assert not (tmp_path / "r3").exists()  # a refused render leaves no folder
    assert main(["render", str(ply), "--orbit", "3", "--views", "2", "--out", str(tmp_path / "r4")]) == 2
    assert "--views picks views of a camera path" in capsys.readouterr().err


def test_without_cameras_an_arc_of_views(captured, tmp_path, capsys):
    import shutil

    ply, _ = captured
    lone = tmp_path / "lone.ply"
    shutil.copy(ply, lone)
    out = tmp_path / "r"
    assert main(["render", str(lone), "--orbit", "3", "--size", "40", "30", "--what", "color", "--out",
                 str(out), "--device", "cpu"]) == 0
    assert "arc over the observed side, 40x30" in capsys.readouterr().out
    assert sorted(p.name for p in out.glob("*.png")) == [f"orbit{i:03d}_color.png" for i in range(3)]


def test_cameras_json_survives_a_read_back(captured):
    ply, data = captured
    cams = read_cameras_json(ply.with_name("cameras.json"))
    ref = load_dataset(data).cameras
    assert [c.image_name for c in cams] == [c.image_name for c in ref]
    assert all(torch.allclose(a.viewmat.double(), b.viewmat.double(), atol=1e-6) for a, b in zip(cams, ref))


@pytest.mark.parametrize("device", DEVICES)
def test_pictures_are_the_single_camera_renders(captured, tmp_path, monkeypatch, device):
    """The views render several to a pass (render_view_chunks); each picture equals the one a
    render of its camera alone gives, byte for byte, across a chunk boundary."""
    import tiger.cli.render
    from tiger.scene import GaussianScene, render_view_chunks
    from tiger.utils.images import depth_picture, to_uint8

    chunks = []

    def four_a_pass(scene, cameras, *args, views_per_pass, **kwargs):  # 6 views: chunks of 4 and 2
        assert views_per_pass == 8  # the default, memory permitting (tiny views here)
        for first, outputs in render_view_chunks(scene, cameras, *args, views_per_pass=4, **kwargs):
            chunks.append((first, outputs["color"].shape[0]))
            yield first, outputs

    monkeypatch.setattr(tiger.cli.render, "render_view_chunks", four_a_pass)
    ply, _ = captured
    out = tmp_path / "r"
    assert main(["render", str(ply), "--views", "all", "--what", "color", "depth", "alpha", "--out", str(out),
                 "--device", device]) == 0
    scene = GaussianScene.load_ply(ply).to(device=device)
    cams = read_cameras_json(ply.parent / "cameras.json")
    for i, cam in enumerate(cams):
        one = scene.render(cam)
        color = np.array(Image.open(out / f"{i:03d}_color.png"))
        assert np.array_equal(color, to_uint8(one["color"].clamp(0, 1))), i
        assert np.array_equal(np.array(Image.open(out / f"{i:03d}_alpha.png")), to_uint8(one["alpha"])), i
        depth = np.array(Image.open(out / f"{i:03d}_depth.png").convert("RGB"))
        assert np.array_equal(depth, to_uint8(depth_picture(one["depth"], one["alpha"] > 0.5))[..., :3]), i
    assert chunks == [(0, 4), (4, 2)]


def test_views_per_pass_follows_free_memory(monkeypatch):
    """Several views render together only as far as half the free memory holds them by the render
    estimate (80 bytes a pixel for RGB: 12 per channel + 44), between 1 and render_view_chunks'
    default of 8."""
    from tiger.cli import common

    one = 100 * 100 * (3 * 12 + 44)
    assert common.render_bytes(100, 100) == one
    for free, want in ((10 * one, 5), (2 * one, 1), (one // 3, 1), (10**15, 8)):
        monkeypatch.setattr(common, "available_bytes", lambda device, free=free: free)
        assert common.views_per_pass(100, 100, torch.device("cpu")) == want, free
