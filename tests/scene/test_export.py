"""tiger.scene.export and `tiger export`: each format decoded by an independent reader written
from the format's published layout, compared with the scene within the format's quantisation."""
from __future__ import annotations

import gzip
import math
import struct

import numpy as np
import pytest
import torch

from tiger.cli.main import main
from tiger.scene import GaussianScene
from tiger.scene.export import compressed_ply_bytes, splat_bytes, spz_bytes

C0 = 0.28209479177387814
N = 600  # three chunks of the compressed PLY, the last one partial


@pytest.fixture(scope="module")
def scene() -> GaussianScene:
    g = torch.Generator().manual_seed(3)
    return GaussianScene(
        means=torch.rand(N, 3, generator=g) * 4 - 2,
        log_scales=torch.rand(N, 3, generator=g) * 4 - 6,
        quats=torch.randn(N, 4, generator=g),
        opacity_logits=torch.randn(N, generator=g) * 2,
        sh_dc=(torch.rand(N, 3, generator=g) - 0.5) * 3,  # colours 0.5 + C0 * dc inside [0, 1]
        sh_rest=(torch.rand(N, 15, 3, generator=g) - 0.5) * 0.6,  # SH degree 3
    )


def _unit_quats(scene):
    return torch.nn.functional.normalize(scene.quats, dim=1).numpy()


def _same_rotation(a: np.ndarray, b: np.ndarray, tol: float) -> None:
    """Quaternions [N, 4] (w, x, y, z) a and b are the same rotations (q ~ -q)."""
    dot = np.abs((a / np.linalg.norm(a, axis=1, keepdims=True) * b).sum(1))
    assert dot.min() > 1 - tol, dot.min()


# -- antimatter15 .splat: 32 bytes, pos f32x3, scale f32x3, RGBA u8x4, rotation u8x4 (w, x, y, z)
def read_splat(data: bytes) -> dict:
    assert len(data) % 32 == 0
    n = len(data) // 32
    out = {k: [] for k in ("pos", "scale", "rgba", "rot")}
    for i in range(n):
        rec = data[32 * i: 32 * (i + 1)]
        out["pos"].append(struct.unpack("<3f", rec[0:12]))
        out["scale"].append(struct.unpack("<3f", rec[12:24]))
        out["rgba"].append(tuple(rec[24:28]))
        out["rot"].append(tuple(rec[28:32]))
    return {k: np.array(v, dtype=np.float64) for k, v in out.items()}


def test_splat_round_trip(scene):
    d = read_splat(splat_bytes(scene))
    assert len(d["pos"]) == N
    np.testing.assert_allclose(d["pos"], scene.means.numpy(), rtol=0, atol=1e-6)
    np.testing.assert_allclose(d["scale"], scene.log_scales.exp().numpy(), rtol=1e-6)
    np.testing.assert_allclose(d["rgba"][:, :3] / 255, (0.5 + C0 * scene.sh_dc).numpy(), atol=0.5 / 255 + 1e-6)
    np.testing.assert_allclose(d["rgba"][:, 3] / 255, torch.sigmoid(scene.opacity_logits).numpy(),
                               atol=0.5 / 255 + 1e-6)
    _same_rotation((d["rot"] - 128) / 128, _unit_quats(scene), 2e-3)


# -- Niantic .spz v2: gzip; header <u32 magic, u32 version, u32 count, u8 degree, u8 frac bits,
# u8 flags, u8 reserved>; positions (24-bit fixed), alphas, colours, scales, rotations, SH; RUB axes
def read_spz(data: bytes) -> dict:
    raw = gzip.decompress(data)
    magic, version, n, degree, frac, flags, reserved = struct.unpack("<IIIBBBB", raw[:16])
    assert (magic, version, flags, reserved) == (0x5053474E, 2, 0, 0)
    k = {0: 0, 1: 3, 2: 8, 3: 15}[degree]
    off = 16

    def take(count):
        nonlocal off
        chunk = np.frombuffer(raw, dtype=np.uint8, count=count, offset=off).astype(np.int64)
        off += count
        return chunk

    p = take(9 * n).reshape(n, 3, 3)
    fixed = p[..., 0] | (p[..., 1] << 8) | (p[..., 2] << 16)
    fixed = np.where(fixed & 0x800000, fixed - (1 << 24), fixed)
    out = {"pos": fixed / (1 << frac), "alpha": take(n) / 255,
           "dc": (take(3 * n).reshape(n, 3) / 255 - 0.5) / 0.15,
           "log_scale": take(3 * n).reshape(n, 3) / 16 - 10}
    xyz = take(3 * n).reshape(n, 3) / 127.5 - 1
    w = np.sqrt(np.clip(1 - (xyz ** 2).sum(1), 0, 1))
    out["quat"] = np.concatenate([w[:, None], xyz], 1)
    out["sh"] = (take(3 * k * n).reshape(n, k, 3) - 128) / 128
    assert off == len(raw), "trailing bytes"
    return out


def test_spz_round_trip(scene):
    d = read_spz(spz_bytes(scene))
    rub = np.array([1.0, -1.0, -1.0])  # SPZ is right-up-back, the scene right-down-front
    np.testing.assert_allclose(d["pos"] * rub, scene.means.numpy(), atol=0.5 / 4096 + 1e-6)
    np.testing.assert_allclose(d["alpha"], torch.sigmoid(scene.opacity_logits).numpy(), atol=0.5 / 255 + 1e-6)
    np.testing.assert_allclose(d["dc"], scene.sh_dc.numpy(), atol=0.5 / 255 / 0.15 + 1e-6)
    np.testing.assert_allclose(d["log_scale"], scene.log_scales.numpy(), atol=0.5 / 16 + 1e-6)
    q = _unit_quats(scene) * np.array([1, 1, -1, -1])  # half turn about x: (w, x, -y, -z)
    q = np.where(q[:, :1] < 0, -q, q)  # stored with w >= 0
    np.testing.assert_allclose(d["quat"][:, 1:], q[:, 1:], atol=0.5 / 127.5 + 1e-6)
    # w comes from |q| = 1: exact up to the x, y, z rounding (loose only where w is near 0)
    big_w = q[:, 0] > 0.3
    _same_rotation(d["quat"][big_w], q[big_w], 2e-4)
    # SH under (x, y, z) -> (x, -y, -z): the sign of each real basis function (y, z odd -> -1)
    x, y, z = np.random.default_rng(0).normal(size=(3, 64))
    basis, flipped = np.stack(_basis(x, y, z)), np.stack(_basis(x, -y, -z))
    signs = np.sign((basis * flipped).sum(1))
    np.testing.assert_allclose(d["sh"] * signs[None, :, None], scene.sh_rest.numpy(), atol=0.5 / 128 + 1e-6)


def _basis(x, y, z):
    """The real SH basis functions of degrees 1-3 (m = -l..l) up to their positive constants."""
    return [y, z, x, x * y, y * z, 3 * z * z - 1, x * z, x * x - y * y, y * (3 * x * x - y * y), x * y * z,
            y * (5 * z * z - 1), z * (5 * z * z - 3), x * (5 * z * z - 1), z * (x * x - y * y), x * (x * x - 3 * y * y)]


# -- PlayCanvas compressed PLY: element chunk (float min/max per 256), vertex packed u32 x4, sh u8
def read_compressed_ply(data: bytes) -> dict:
    end = data.index(b"end_header\n") + len(b"end_header\n")
    lines = data[:end].decode("ascii").splitlines()
    assert lines[0] == "ply" and lines[1] == "format binary_little_endian 1.0"
    elements, cur = [], None
    for line in lines[2:]:
        parts = line.split()
        if parts[0] == "element":
            cur = (parts[1], int(parts[2]), [])
            elements.append(cur)
        elif parts[0] == "property":
            cur[2].append((parts[1], parts[2]))
    types = {"float": "<f4", "uint": "<u4", "uchar": "u1"}
    off, out = end, {}
    for name, count, props in elements:
        dt = np.dtype([(p, types[t]) for t, p in props])
        out[name] = np.frombuffer(data, dtype=dt, count=count, offset=off)
        off += dt.itemsize * count
    assert off == len(data)
    return out


def _decode_compressed(el: dict) -> dict:
    ch, v = el["chunk"], el["vertex"]
    n = len(v)
    c = ch[np.arange(n) // 256]

    def unpack(word, lo, hi):
        bits = [(word >> 21) & 2047, (word >> 11) & 1023, word & 2047]
        t = np.stack([bits[0] / 2047, bits[1] / 1023, bits[2] / 2047], 1)
        return lo + t * (hi - lo)

    def box(prefix):
        lo = np.stack([c[f"min_{prefix}{a}"] for a in "xyz"], 1).astype(np.float64)
        hi = np.stack([c[f"max_{prefix}{a}"] for a in "xyz"], 1).astype(np.float64)
        return lo, hi

    pos = unpack(v["packed_position"].astype(np.int64), *box(""))
    log_scale = unpack(v["packed_scale"].astype(np.int64), *box("scale_"))
    col = v["packed_color"].astype(np.int64)
    b = np.stack([(col >> 24) & 255, (col >> 16) & 255, (col >> 8) & 255, col & 255], 1) / 255
    lo = np.stack([c[f"min_{k}"] for k in "rgb"], 1)
    hi = np.stack([c[f"max_{k}"] for k in "rgb"], 1)
    rgb = lo + b[:, :3] * (hi - lo)
    rot = v["packed_rotation"].astype(np.int64)
    largest = rot >> 30
    three = np.stack([(rot >> 20) & 1023, (rot >> 10) & 1023, rot & 1023], 1) / 1023
    three = (three - 0.5) / (math.sqrt(2) * 0.5)
    q = np.zeros((n, 4))
    for i in range(n):
        others = [j for j in range(4) if j != largest[i]]
        q[i, others] = three[i]
        q[i, largest[i]] = math.sqrt(max(0.0, 1 - (three[i] ** 2).sum()))
    sh = None
    if "sh" in el:
        raw = np.stack([el["sh"][name] for name in el["sh"].dtype.names], 1) / 255
        sh = ((raw - 0.5) * 8).reshape(n, 3, -1).transpose(0, 2, 1)  # channel-major f_rest_*
    return {"pos": pos, "log_scale": log_scale, "rgb": rgb, "alpha": b[:, 3], "quat": q, "sh": sh,
            "chunk_span": {"pos": box(""), "scale": box("scale_"), "rgb": (lo, hi)}}


def test_compressed_ply_round_trip(scene):
    el = read_compressed_ply(compressed_ply_bytes(scene))
    assert len(el["chunk"]) == math.ceil(N / 256) and len(el["vertex"]) == N == len(el["sh"])
    d = _decode_compressed(el)
    # the writer reorders the Gaussians (Morton order): match each decoded one to the nearest original
    dist = torch.cdist(torch.from_numpy(d["pos"]), scene.means.double())
    idx = dist.argmin(1).numpy()
    assert sorted(idx.tolist()) == list(range(N)), "every Gaussian written once"
    (plo, phi), (slo, shi), (clo, chi) = (d["chunk_span"][k] for k in ("pos", "scale", "rgb"))
    step = np.array([2047, 1023, 2047])
    assert (np.abs(d["pos"] - scene.means.numpy()[idx]) <= (phi - plo) / step / 2 + 1e-5).all()
    assert (np.abs(d["log_scale"] - scene.log_scales.numpy()[idx]) <= (shi - slo) / step / 2 + 1e-5).all()
    want_rgb = (0.5 + C0 * scene.sh_dc).numpy()[idx]
    assert (np.abs(d["rgb"] - want_rgb) <= (chi - clo) / 255 / 2 + 1e-5).all()
    np.testing.assert_allclose(d["alpha"], torch.sigmoid(scene.opacity_logits).numpy()[idx], atol=0.5 / 255 + 1e-6)
    _same_rotation(d["quat"], _unit_quats(scene)[idx], 1e-3)
    np.testing.assert_allclose(d["sh"], scene.sh_rest.numpy()[idx], atol=0.5 * 8 / 255 + 1e-5)


def test_export_command(scene, tmp_path, capsys):
    ply = tmp_path / "scene.ply"
    scene.save_ply(ply)
    for fmt, name in (("splat", "s.splat"), ("spz", "s.spz"), ("ply-compressed", "s.compressed.ply")):
        assert main(["export", str(ply), "--format", fmt, "--out", str(tmp_path / name)]) == 0, fmt
        assert (tmp_path / name).stat().st_size > 0
    assert len(read_spz((tmp_path / "s.spz").read_bytes())["pos"]) == N
    assert main(["export", str(ply), "--format", "spz", "--out", str(tmp_path / "s.spz")]) == 2
    assert "--force" in capsys.readouterr().err
    assert main(["export", str(ply), "--format", "spz", "--out", str(tmp_path / "s.spz"), "--force"]) == 0
