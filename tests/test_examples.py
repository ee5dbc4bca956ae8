"""The scripts in examples/ run end to end on tiny inputs made here (subprocesses, as a user runs them)."""
from __future__ import annotations

import json
import math
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

ROOT = Path(__file__).resolve().parents[1]
EXAMPLES = ROOT / "examples"
SCRIPTS = ("render_turntable.py", "embed_and_query_colmap.py", "evaluate_lerf.py")


def run(script: str, *args: str, timeout: float = 120) -> subprocess.CompletedProcess:
    env = {**os.environ, "OMP_NUM_THREADS": "2", "PYTHONWARNINGS": "ignore"}
    env.pop("TIGER_MODELS", None)
    return subprocess.run([sys.executable, str(EXAMPLES / script), *map(str, args)], capture_output=True,
                          text=True, timeout=timeout, env=env, cwd=str(ROOT))


def load_example(script: str):
    """The example as a module (its ``main``/``cli`` called in-process: no interpreter start-up)."""
    import importlib.util

    spec = importlib.util.spec_from_file_location(f"example_{Path(script).stem}", EXAMPLES / script)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def cli_error(script: str, *args) -> str:
    """Run the example's ``cli`` expecting a one-line error; returns the message."""
    with pytest.raises(SystemExit) as e:
        load_example(script).cli([str(a) for a in args])
    assert e.value.code not in (0, None)
    return str(e.value.code)


def tabletop_gaussian_scene(density: float = 0.1):
    from tiger.demo import tabletop_scene

    lab = tabletop_scene(density)
    return lab, lab.scene


@pytest.mark.parametrize("script", SCRIPTS)
def test_help(script, capsys):
    with pytest.raises(SystemExit) as e:
        load_example(script).cli(["--help"])
    assert e.value.code == 0
    out = capsys.readouterr().out
    assert "usage:" in out and "example:" in out
    doc = (EXAMPLES / script).read_text().split('"""')[1]
    assert len(doc.strip().splitlines()) > 3  # a real docstring, not a one-liner


def test_help_as_a_script():
    r = run("evaluate_lerf.py", "--help", timeout=60)
    assert r.returncode == 0 and "usage:" in r.stdout, r.stderr


# ------------------------------------------------------------------------ render_turntable
def test_render_turntable(tmp_path):
    from tiger import rasterize_gaussians
    from tiger.render.views import orbit_viewmats, pinhole_K
    from tiger.scene.sh import sh_to_rgb

    lab, scene = tabletop_gaussian_scene()
    scene.save_ply(tmp_path / "s.ply")
    w, h, n = 48, 36, 4
    r = run("render_turntable.py", tmp_path / "s.ply", "--out", tmp_path / "tt", "--views", n, "--width", w,
            "--height", h, "--center", 0, -0.2, 0, "--radius", 3.0, "--elevation", 30, "--video", "gif")
    assert r.returncode == 0, r.stderr
    frames = sorted((tmp_path / "tt").glob("frame_*.png"))
    assert [f.name for f in frames] == [f"frame_{i:04d}.png" for i in range(n)]
    # every frame equals an independent render of the labelled scene from the same orbit camera
    views = orbit_viewmats(n, center=(0, -0.2, 0), radius=3.0, elevation_deg=30)
    for i in (0, 2):
        with torch.no_grad():
            ref = rasterize_gaussians(scene.means, scene.quats, scene.scales, scene.opacities,
                                      sh_to_rgb(scene.sh_dc).clamp_min(0), views[i], pinhole_K(w, h), w, h,
                                      background=torch.ones(3))["color"].clamp(0, 1)
        got = np.asarray(Image.open(frames[i]), dtype=np.float64) / 255
        assert got.shape == (h, w, 3)
        assert np.abs(got - ref.numpy()).max() <= 1.5 / 255
    imgs = [np.asarray(Image.open(f), dtype=np.int32) for f in frames]
    assert np.abs(imgs[0] - imgs[2]).mean() > 1  # opposite sides of the table differ
    with Image.open(tmp_path / "tt" / "turntable.gif") as gif:
        assert gif.n_frames == n and gif.size == (w, h)


def test_render_turntable_auto_video_and_errors(tmp_path):
    _, scene = tabletop_gaussian_scene(0.05)
    scene.save_ply(tmp_path / "s.ply")
    r = run("render_turntable.py", tmp_path / "s.ply", "--out", tmp_path / "tt", "--views", 2, "--width", 24,
            "--height", 18)
    assert r.returncode == 0, r.stderr
    videos = list((tmp_path / "tt").glob("turntable.*"))
    assert len(videos) == 1 and videos[0].suffix in (".mp4", ".webm", ".gif") and videos[0].stat().st_size > 0
    assert "missing.ply" in cli_error("render_turntable.py", tmp_path / "missing.ply", "--out", tmp_path / "x")
    assert "--views" in cli_error("render_turntable.py", tmp_path / "s.ply", "--out", tmp_path / "x", "--views", 0)
    # An explicit MP4 request gets H.264 where an encoder has it, else one line saying so (never a
    # silent GIF, nor MPEG-4 Part 2 that browsers do not play).
    r = run("render_turntable.py", tmp_path / "s.ply", "--out", tmp_path / "m", "--views", 2,
            "--width", 16, "--height", 12, "--video", "mp4")
    if r.returncode == 0:
        assert [p.name for p in (tmp_path / "m").glob("turntable.*")] == ["turntable.mp4"]
    else:
        assert "cannot write MP4" in r.stderr and "Traceback" not in r.stderr, r.stderr
        assert not list((tmp_path / "m").glob("turntable.*"))
    (tmp_path / "bad.ply").write_text("ply\nformat ascii 1.0\nelement vertex 2\nend_header\n")
    assert "bad.ply" in cli_error("render_turntable.py", tmp_path / "bad.ply", "--out", tmp_path / "x")


# ------------------------------------------------------------------ embed_and_query_colmap
def rotmat_to_qvec(R: torch.Tensor) -> list:
    """COLMAP's (qw, qx, qy, qz) of a rotation matrix (Shepperd's method)."""
    R = R.double()
    tr = float(R.trace())
    if tr > 0:
        s = 2 * math.sqrt(tr + 1)
        q = [s / 4, (R[2, 1] - R[1, 2]) / s, (R[0, 2] - R[2, 0]) / s, (R[1, 0] - R[0, 1]) / s]
    else:
        i = int(torch.argmax(torch.diagonal(R)))
        j, k = (i + 1) % 3, (i + 2) % 3
        s = 2 * math.sqrt(1 + R[i, i] - R[j, j] - R[k, k])
        q = [0.0] * 4
        q[0] = (R[k, j] - R[j, k]) / s
        q[1 + i], q[1 + j], q[1 + k] = s / 4, (R[j, i] + R[i, j]) / s, (R[k, i] + R[i, k]) / s
    return [float(v) for v in q]


def write_colmap_text(root: Path, lab, scene, n: int = 3, w: int = 64, h: int = 48) -> list:
    """``root/sparse/0/{cameras,images,points3D}.txt`` and ``root/images/*.png`` rendered from
    ``n`` orbit views; returns the world->camera matrices."""
    from tiger.render.views import orbit_viewmats, pinhole_K
    from tiger.render import Camera
    from tiger.utils.images import save_png

    model = root / "sparse" / "0"
    model.mkdir(parents=True)
    K = pinhole_K(w, h)
    (model / "cameras.txt").write_text(
        f"# Camera list\n1 PINHOLE {w} {h} {float(K[0, 0])} {float(K[1, 1])} {float(K[0, 2])} {float(K[1, 2])}\n")
    lines, views = ["# Image list"], orbit_viewmats(n, start_deg=10.0)
    for i, V in enumerate(views):
        q, t = rotmat_to_qvec(V[:3, :3]), V[:3, 3].double().tolist()
        lines += [f"{i + 1} {' '.join(map(str, q))} {' '.join(map(str, t))} 1 img{i}.png", ""]
        with torch.no_grad():
            save_png(root / "images" / f"img{i}.png",
                     scene.render(Camera(V, K, w, h), background=torch.ones(3))["color"].clamp(0, 1))
    (model / "images.txt").write_text("\n".join(lines) + "\n")
    pts = scene.means[:: max(1, len(scene) // 50)]
    (model / "points3D.txt").write_text("".join(
        f"{k + 1} {float(p[0])} {float(p[1])} {float(p[2])} 128 128 128 0.5\n" for k, p in enumerate(pts)))
    return views


def test_colmap_fixture_loads_back(tmp_path):
    """The test's own COLMAP writer is right: the loader returns the cameras it was given."""
    from tiger.scene.dataset import load_colmap

    lab, scene = tabletop_gaussian_scene(0.05)
    views = write_colmap_text(tmp_path, lab, scene)
    cams = load_colmap(tmp_path).cameras
    assert [c.image_name for c in cams] == ["img0.png", "img1.png", "img2.png"]
    for c, V in zip(cams, views):
        assert torch.allclose(c.viewmat.double(), V.double(), atol=1e-5)


def test_embed_and_query_colmap_random_models(tmp_path):
    from tiger.scene import GaussianScene

    lab, scene = tabletop_gaussian_scene(0.1)
    write_colmap_text(tmp_path / "data", lab, scene)
    scene.save_ply(tmp_path / "scene.ply")
    out = tmp_path / "out"
    args = [tmp_path / "data", tmp_path / "scene.ply", "--out", out, "--random-models", "--query", "mug",
            "--query", "a ball", "--upsampler", "bilinear", "--sam-points", 4, "--clip-long-side", 64,
            "--feature-long-side", 32, "--steps", 15, "--lr", 0.01, "--device", "cpu"]
    r = run("embed_and_query_colmap.py", *args, timeout=240)
    assert r.returncode == 0, r.stderr[-3000:]
    lang = GaussianScene.load_ply(out / "scene_lang.ply")
    # the tiny CLIP's projection is 24-d: PCA dimension min(64, 24)
    assert lang.lang is not None and lang.lang.shape == (len(scene), 24)
    assert lang.lang_pca_basis.shape == (24, 24)
    assert torch.equal(lang.means, scene.means)  # geometry frozen
    assert len(list((out / "features" / "features").glob("*.pt"))) == 3
    for slug in ("mug", "a_ball"):
        sel = GaussianScene.load_ply(out / f"selection_{slug}.ply")
        assert 0 < len(sel) <= len(scene)
        # the selection is a subset of the scene's Gaussians, with their trained L
        idx = torch.cdist(sel.means, lang.means).argmin(1)
        assert torch.equal(lang.means[idx], sel.means) and torch.allclose(lang.lang[idx], sel.lang)
        assert len(list((out / "heatmaps").glob(f"{slug}_*.png"))) == 2
    assert "'mug':" in r.stdout and "'a ball':" in r.stdout


def test_embed_and_query_colmap_errors(tmp_path, monkeypatch):
    monkeypatch.delenv("TIGER_MODELS", raising=False)
    msg = cli_error("embed_and_query_colmap.py", tmp_path / "nodata", tmp_path / "s.ply", "--out", tmp_path / "o",
                    "--query", "x", "--random-models")
    assert "nodata" in msg
    (tmp_path / "empty").mkdir()
    lab, scene = tabletop_gaussian_scene(0.05)
    scene.save_ply(tmp_path / "s.ply")
    msg = cli_error("embed_and_query_colmap.py", tmp_path / "empty", tmp_path / "s.ply", "--out", tmp_path / "o",
                    "--query", "x", "--random-models")
    assert "no COLMAP model" in msg
    write_colmap_text(tmp_path / "data", lab, scene, n=2, w=16, h=12)
    (tmp_path / "nomodels").mkdir()
    msg = cli_error("embed_and_query_colmap.py", tmp_path / "data", tmp_path / "s.ply", "--out", tmp_path / "o",
                    "--query", "x", "--models", tmp_path / "nomodels")
    assert "model 'clip' not found" in msg and "nomodels" in msg


# --------------------------------------------------------------------------- evaluate_lerf
def write_lerf_fixture(root: Path, name: str, seed: int, size: int = 128, views: int = 3):
    """A LERF-OVS-layout scene: ``root/label/<name>/frame_XXXXX.{json,jpg}`` (boxes and polygons of
    the rendered objects), ``root/<name>/transforms.json`` (its cameras) and a PLY with ``lang_*``."""
    from tiger.scene import render_rgb
    from tiger.testing.labelled_scene import label_masks, make_labelled_scene

    ls = make_labelled_scene(views=views, seed=seed)
    g = torch.Generator().manual_seed(seed)
    s = ls.scene
    s.lang = ls.label_lang[ls.labelled.labels] + 0.3 * torch.randn(len(ls.labelled.labels), 64, generator=g) / 8
    labels, data = root / "label" / name, root / name
    labels.mkdir(parents=True)
    data.mkdir(parents=True)
    gl = torch.diag(torch.tensor([1.0, -1.0, -1.0, 1.0], dtype=torch.float64))
    frames = []
    for v, cam in enumerate(ls.cameras):
        c = cam.resized(size, size)
        masks = label_masks(ls, c)
        objects = []
        for k, lab in enumerate(ls.labelled.names):
            if masks[k].sum() < 100:
                continue
            ys, xs = torch.nonzero(masks[k], as_tuple=True)
            x0, y0, x1, y1 = int(xs.min()), int(ys.min()), int(xs.max()), int(ys.max())
            objects.append({"category": lab, "bbox": [x0, y0, x1, y1],
                            "segmentation": [[x0, y0], [x1, y0], [x1, y1], [x0, y1]]})
        stem = f"frame_{v + 1:05d}"
        (labels / f"{stem}.json").write_text(json.dumps(
            {"info": {"name": f"{stem}.jpg", "width": size, "height": size}, "objects": objects}))
        Image.fromarray((render_rgb(s, [c])[0].numpy() * 255).astype(np.uint8)).save(labels / f"{stem}.jpg")
        frames.append({"file_path": f"../label/{name}/{stem}.jpg",
                       "transform_matrix": (torch.linalg.inv(c.viewmat.double()) @ gl).tolist()})
    K = ls.cameras[0].K * size / ls.cameras[0].width
    (data / "transforms.json").write_text(json.dumps(
        {"fl_x": float(K[0, 0]), "fl_y": float(K[1, 1]), "cx": float(K[0, 2]), "cy": float(K[1, 2]),
         "w": size, "h": size, "frames": frames}))
    s.save_ply(tmp_ply(root, name))
    return ls


def tmp_ply(root: Path, name: str) -> Path:
    return root / "outputs" / name / "scene_lang.ply"


def test_evaluate_lerf(tmp_path):
    root = tmp_path / "lerf_ovs"
    ls = write_lerf_fixture(root, "toyroom", 0)
    ls.encoder.save(tmp_path / "text.pt")  # CLIP-space embeddings of the labels
    r = run("evaluate_lerf.py", root, "--ply", str(root / "outputs" / "{scene}" / "scene_lang.ply"),
            "--out", tmp_path / "out", "--text-embeddings", tmp_path / "text.pt", "--device", "cpu",
            "--filter-size", 15,  # the 30 px filter is for ~1000 px frames; these are 128 px
            timeout=180)
    assert r.returncode == 0, r.stderr[-3000:]
    assert "| toyroom |" in r.stdout and "**100.0**" in r.stdout
    res = json.loads((tmp_path / "out" / "results.json").read_text())
    assert res["mean_accuracy"] == 1.0
    assert len(list((tmp_path / "out" / "toyroom").rglob("*.png"))) >= 9
    # a text table that lacks a category is a clear error
    torch.save({k: v for k, v in ls.encoder.table.items() if k != "teddy bear"}, tmp_path / "short.pt")
    msg = cli_error("evaluate_lerf.py", root, "--ply", str(root / "outputs" / "{scene}" / "scene_lang.ply"),
                    "--out", tmp_path / "out2", "--text-embeddings", tmp_path / "short.pt", "--scenes", "toyroom",
                    "--no-pictures", "--device", "cpu")
    assert "teddy bear" in msg
    assert "{scene}" in cli_error("evaluate_lerf.py", root, "--ply", "no_pattern.ply", "--out", tmp_path / "o3",
                                  "--text-embeddings", tmp_path / "text.pt")
    assert "nowhere" in cli_error("evaluate_lerf.py", root, "--ply", "{scene}.ply", "--out", tmp_path / "o3",
                                  "--text-embeddings", tmp_path / "text.pt", "--scenes", "nowhere")
