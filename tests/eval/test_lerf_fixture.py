"""End to end on a LERF-OVS-layout fixture: label JSONs + images written from a synthetic scene."""
from __future__ import annotations

import json

import numpy as np
import pytest
import torch
from PIL import Image

from tiger.eval import lerf
from tiger.testing.labelled_scene import label_masks, make_labelled_scene

SIZE = 256


def _view(cam, size):
    return cam.resized(size, size)


def _hull(mask: torch.Tensor) -> list:
    """Convex hull of the mask's pixels as [[x, y], ...] (the shape of a LabelMe polygon)."""
    from scipy.spatial import ConvexHull

    ys, xs = torch.nonzero(mask, as_tuple=True)
    pts = np.stack([xs.numpy(), ys.numpy()], 1).astype(np.float64)
    return pts[ConvexHull(pts).vertices].tolist()


def write_fixture(root, name: str, seed: int, views: int = 3):
    """``root/label/<name>/frame_XXXXX.{json,jpg}`` for ``views`` cameras; returns the scene."""
    from tiger.scene import render_rgb

    ls = make_labelled_scene(views=views, seed=seed)
    g = torch.Generator().manual_seed(seed)
    ls.scene.lang = ls.label_lang[ls.labelled.labels] + 0.3 * torch.randn(len(ls.labelled.labels), 64, generator=g) / 8
    folder = root / "label" / name
    folder.mkdir(parents=True)
    cams = []
    for v, cam in enumerate(ls.cameras):
        c = _view(cam, SIZE)
        cams.append(c)
        masks = label_masks(ls, c)
        objects = []
        for k, lab in enumerate(ls.labelled.names):
            if masks[k].sum() < 300:
                continue
            ys, xs = torch.nonzero(masks[k], as_tuple=True)
            objects.append({"category": lab, "bbox": [int(xs.min()), int(ys.min()), int(xs.max()), int(ys.max())],
                            "segmentation": _hull(masks[k])})
        stem = f"frame_{v + 1:05d}"
        (folder / f"{stem}.json").write_text(json.dumps(
            {"info": {"name": f"{stem}.jpg", "width": SIZE, "height": SIZE}, "objects": objects}))
        rgb = (render_rgb(ls.scene, [c])[0].numpy() * 255).astype(np.uint8)
        Image.fromarray(rgb).save(folder / f"{stem}.jpg")
    return ls, cams


def test_end_to_end_api(tmp_path, capsys):
    results = []
    for name, seed in (("toyroom", 0), ("toykitchen", 5)):
        ls, cams = write_fixture(tmp_path, name, seed)
        labels = lerf.load_scene_labels(tmp_path / "label" / name)
        assert len(labels) == 3 and all(fr.image_path is not None for fr in labels)
        fn = lerf.scene_relevancy_fn(ls.scene, cams, labels, encoder=ls.encoder)
        # Pictures for the first scene only (matplotlib dominates the run time).
        res = lerf.evaluate_scene(name, labels, fn, out_dir=tmp_path / "out", progress=False,
                                  pictures=name == "toyroom")
        assert len(res.queries) >= 10
        assert res.accuracy == 1.0, [(q.frame, q.category) for q in res.queries if not q.hit]
        assert res.miou > 0.3
        results.append(res)
    table = lerf.format_table(results)
    print(table)
    assert "| **mean over scenes** |" in table and "**100.0**" in table
    pics = list((tmp_path / "out").rglob("*.png"))
    assert len(pics) == len(results[0].queries) and all(p.stat().st_size > 1000 for p in pics)


def _write_transforms(path, cams):
    """NeRF transforms.json (camera-to-world, OpenGL axes) for OpenCV world->camera views."""
    flip = torch.diag(torch.tensor([1.0, -1.0, -1.0, 1.0], dtype=torch.float64))
    c0 = cams[0]
    frames = [{"file_path": f"label/toyroom/frame_{i + 1:05d}.jpg",
               "transform_matrix": (torch.linalg.inv(c.viewmat.double()) @ flip).tolist()} for i, c in enumerate(cams)]
    path.write_text(json.dumps({"fl_x": float(c0.K[0, 0]), "fl_y": float(c0.K[1, 1]), "cx": float(c0.K[0, 2]),
                                "cy": float(c0.K[1, 2]), "w": c0.width, "h": c0.height, "frames": frames}))


def test_end_to_end_cli(tmp_path, capsys):
    ls, cams = write_fixture(tmp_path, "toyroom", 0)
    ls.scene.save_ply(tmp_path / "toyroom.ply")
    _write_transforms(tmp_path / "transforms.json", cams)
    ls.encoder.save(tmp_path / "text.pt")
    rc = lerf.main(["--labels", str(tmp_path / "label"), "--scene", f"toyroom={tmp_path / 'toyroom.ply'}",
                    "--data", f"toyroom={tmp_path / 'transforms.json'}", "--text-embeddings",
                    str(tmp_path / "text.pt"), "--out", str(tmp_path / "out"), "--device", "cpu"])
    out = capsys.readouterr().out
    assert rc == 0
    assert "| toyroom |" in out and "**100.0**" in out
    data = json.loads((tmp_path / "out" / "results.json").read_text())
    assert data["mean_accuracy"] == 1.0


def test_cli_errors(tmp_path):
    with pytest.raises(SystemExit, match="NAME=PATH"):
        lerf.main(["--labels", str(tmp_path), "--scene", "noequals", "--out", str(tmp_path)])
    with pytest.raises(SystemExit, match="no --data"):
        lerf.main(["--labels", str(tmp_path), "--scene", "a=b.ply", "--out", str(tmp_path)])
