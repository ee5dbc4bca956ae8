"""An independent minimal COLMAP model writer for the tests (from COLMAP's documented
text and binary layouts; shares no code with tiger.scene.colmap)."""
from __future__ import annotations

import struct
from pathlib import Path

MODEL_IDS = {"SIMPLE_PINHOLE": 0, "PINHOLE": 1, "SIMPLE_RADIAL": 2, "RADIAL": 3, "OPENCV": 4,
             "OPENCV_FISHEYE": 5, "FULL_OPENCV": 6}


def write_model(folder: Path, cameras: list, images: list, points: list, binary: bool) -> None:
    """cameras: (id, model, w, h, params); images: (id, qvec4, tvec3, cam_id, name, pts2d);
    points: (id, xyz3, rgb3, error, track[(img, idx)])."""
    folder.mkdir(parents=True, exist_ok=True)
    if binary:
        b = struct.pack("<Q", len(cameras))
        for cid, model, w, h, params in cameras:
            b += struct.pack("<iiQQ", cid, MODEL_IDS[model], w, h) + struct.pack(f"<{len(params)}d", *params)
        (folder / "cameras.bin").write_bytes(b)
        b = struct.pack("<Q", len(images))
        for iid, q, t, cid, name, pts in images:
            b += struct.pack("<i4d3di", iid, *q, *t, cid) + name.encode() + b"\x00"
            b += struct.pack("<Q", len(pts)) + b"".join(struct.pack("<ddq", *p) for p in pts)
        (folder / "images.bin").write_bytes(b)
        b = struct.pack("<Q", len(points))
        for pid, xyz, rgb, err, track in points:
            b += struct.pack("<Q3d3BdQ", pid, *xyz, *rgb, err, len(track))
            b += b"".join(struct.pack("<ii", *tr) for tr in track)
        (folder / "points3D.bin").write_bytes(b)
    else:
        lines = ["# Camera list with one line of data per camera:", "#   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]"]
        lines += [f"{cid} {model} {w} {h} " + " ".join(repr(float(p)) for p in params)
                  for cid, model, w, h, params in cameras]
        (folder / "cameras.txt").write_text("\n".join(lines) + "\n")
        lines = ["# Image list with two lines of data per image:"]
        for iid, q, t, cid, name, pts in images:
            lines.append(f"{iid} " + " ".join(repr(float(v)) for v in (*q, *t)) + f" {cid} {name}")
            lines.append(" ".join(f"{x!r} {y!r} {pid}" for x, y, pid in pts))  # may be empty
        (folder / "images.txt").write_text("\n".join(lines) + "\n")
        lines = ["# 3D point list with one line of data per point:"]
        for pid, xyz, rgb, err, track in points:
            lines.append(f"{pid} " + " ".join(repr(float(v)) for v in xyz) + " " + " ".join(map(str, rgb))
                         + f" {err!r} " + " ".join(f"{a} {b}" for a, b in track))
        (folder / "points3D.txt").write_text("\n".join(lines) + "\n")
