"""Scene export to the compact formats web viewers read: antimatter15 ``.splat``, Niantic
``.spz`` (version 2) and PlayCanvas/SuperSplat compressed PLY.

All three are written from a :class:`~tiger.scene.GaussianScene`'s parameters (``means`` [N, 3],
``log_scales`` [N, 3], ``quats`` [N, 4] as w, x, y, z, ``opacity_logits`` [N], ``sh_dc`` [N, 3],
``sh_rest`` [N, K, 3]); language features are not part of any of them. Layouts (little-endian):

``splat``  32 bytes a Gaussian, no header: position f32 x3, scale f32 x3 (linear, exp of the
           log-scale), colour u8 x4 (R, G, B = 0.5 + C0 * f_dc, A = sigmoid(opacity), times
           255), rotation u8 x4 (w, x, y, z of the unit quaternion, 128 + 128 q, clamped).
           View-dependent colour (SH degree > 0) is dropped: the format has none.
``spz``    gzip of: header (u32 magic 0x5053474e, u32 version 2, u32 count, u8 SH degree,
           u8 fractional bits, u8 flags, u8 reserved), then per attribute for all Gaussians:
           positions as 24-bit signed fixed point (3 bytes each, ``FRACTIONAL_BITS``), alphas
           u8 (sigmoid * 255), colours u8 (f_dc * 0.15 * 255 + 127.5), scales u8 ((log + 10) * 16),
           rotations u8 x3 (x, y, z of the quaternion with w >= 0, 127.5 q + 127.5), SH u8
           (128 q + 128, coefficient-major, colour inner). SPZ stores right-up-back axes
           (OpenGL); TIGER's scenes use right-down-front (OpenCV, COLMAP), so y and z are negated
           with the rotations and SH coefficients to match (a half turn about x).
``ply-compressed``  a binary PLY with element ``chunk`` (per 256 Gaussians, float min/max of
           x, y, z, of the log-scales and of the colour r, g, b), element ``vertex`` with u32
           ``packed_position`` (11/10/11 bits of the position within its chunk's box),
           ``packed_rotation`` (2 bits: index of the largest quaternion component, then the
           other three in order, 10 bits each, mapped from [-1/sqrt2, 1/sqrt2]),
           ``packed_scale`` (11/10/11 bits of the log-scale in the chunk's range),
           ``packed_color`` (8 bits each of R, G, B in the chunk's colour range and of the
           opacity), and, with SH, element ``sh`` of u8 ``f_rest_*`` ((v / 8 + 0.5) * 255).
           Gaussians are written in Morton order (:func:`morton_order`) so chunks are compact.
"""
from __future__ import annotations

import gzip
import math
import os
from pathlib import Path
from typing import Union

import numpy as np
import torch

from tiger.utils.io import atomic_write

from .gaussian_scene import GaussianScene

PathLike = Union[str, os.PathLike]
FORMATS = ("splat", "spz", "ply-compressed")
SUFFIXES = {"splat": ".splat", "spz": ".spz", "ply-compressed": ".compressed.ply"}

SH_C0 = 0.28209479177387814
SPZ_MAGIC, SPZ_VERSION, FRACTIONAL_BITS, SPZ_COLOR_SCALE = 0x5053474E, 2, 12, 0.15
CHUNK = 256
#: Sign of each real SH basis function (degrees 1-3, m = -l..l) under (x, y, z) -> (x, -y, -z).
_SH_HALF_TURN_X = np.array([-1, -1, 1,  -1, 1, 1, -1, 1,  -1, 1, -1, -1, 1, -1, 1], dtype=np.float32)


def _params(scene: GaussianScene) -> dict[str, np.ndarray]:
    s = scene.detach().to("cpu", torch.float32)
    if len(s) == 0:
        raise ValueError("tiger.export: the scene holds no Gaussians")
    q = torch.nn.functional.normalize(s.quats, dim=1)
    rest = s.sh_rest if s.sh_rest is not None else torch.zeros(len(s), 0, 3)
    return {"means": s.means.numpy(), "log_scales": s.log_scales.numpy(), "quats": q.numpy(),
            "opacity": torch.sigmoid(s.opacity_logits).numpy(), "sh_dc": s.sh_dc.numpy(),
            "sh_rest": rest.numpy()}


def _u8(x: np.ndarray) -> np.ndarray:
    return np.clip(np.round(x), 0, 255).astype(np.uint8)


def splat_bytes(scene: GaussianScene) -> bytes:
    """The scene as antimatter15 ``.splat`` bytes (32 a Gaussian; see the module notes)."""
    p = _params(scene)
    rec = np.zeros(len(p["means"]), dtype=[("pos", "<f4", 3), ("scale", "<f4", 3), ("rgba", "u1", 4),
                                          ("rot", "u1", 4)])
    rec["pos"] = p["means"]
    rec["scale"] = np.exp(p["log_scales"])
    rec["rgba"][:, :3] = _u8((0.5 + SH_C0 * p["sh_dc"]) * 255)
    rec["rgba"][:, 3] = _u8(p["opacity"] * 255)
    rec["rot"] = _u8(p["quats"] * 128 + 128)
    return rec.tobytes()


def spz_bytes(scene: GaussianScene) -> bytes:
    """The scene as Niantic ``.spz`` (version 2, gzip; see the module notes)."""
    p = _params(scene)
    n, k = len(p["means"]), p["sh_rest"].shape[1]
    degree = {0: 0, 3: 1, 8: 2, 15: 3}.get(k)
    if degree is None:
        raise ValueError(f"tiger.export: {k} SH rest coefficients match no degree 0..3")
    flip = np.array([1.0, -1.0, -1.0], dtype=np.float32)  # right-down-front -> right-up-back
    fixed = np.round(p["means"] * flip * (1 << FRACTIONAL_BITS)).astype(np.int64)
    limit = 1 << 23
    if np.abs(fixed).max(initial=0) >= limit:
        raise ValueError(f"tiger.export: positions reach {np.abs(p['means']).max():.4g}, beyond the "
                         f"{limit / (1 << FRACTIONAL_BITS):g} that SPZ's 24-bit fixed point holds")
    fixed &= 0xFFFFFF  # two's complement, 24 bits
    positions = np.stack([(fixed >> s) & 0xFF for s in (0, 8, 16)], axis=-1).astype(np.uint8)  # [N, 3, 3]
    w, xyz = p["quats"][:, :1], p["quats"][:, 1:] * flip  # half turn about x: (w, x, -y, -z)
    xyz = np.where(w < 0, -xyz, xyz)  # q and -q are the same rotation: keep w >= 0
    rest = p["sh_rest"] * _SH_HALF_TURN_X[:k, None]
    parts = [
        np.array([SPZ_MAGIC, SPZ_VERSION, n], dtype="<u4").tobytes(),
        bytes([degree, FRACTIONAL_BITS, 0, 0]),
        positions.tobytes(),
        _u8(p["opacity"] * 255).tobytes(),
        _u8(p["sh_dc"] * (SPZ_COLOR_SCALE * 255) + 127.5).tobytes(),
        _u8((p["log_scales"] + 10) * 16).tobytes(),
        _u8(xyz * 127.5 + 127.5).tobytes(),
        _u8(rest * 128 + 128).tobytes(),  # [N, K, 3]: coefficient-major, colour inner
    ]
    return gzip.compress(b"".join(parts), compresslevel=6, mtime=0)


def morton_order(means: np.ndarray) -> np.ndarray:
    """Indices [N] sorting positions [N, 3] along a 3D Morton (Z-order) curve of 10 bits an axis."""
    lo, hi = means.min(0), means.max(0)
    cell = np.clip(((means - lo) / np.maximum(hi - lo, 1e-12) * 1023).astype(np.int64), 0, 1023)
    code = np.zeros(len(means), dtype=np.int64)
    for bit in range(10):
        for axis in range(3):
            code |= ((cell[:, axis] >> bit) & 1) << (3 * bit + axis)
    return np.argsort(code, kind="stable")


def _unit(x: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    span = hi - lo
    return np.where(span > 0, (x - lo) / np.where(span > 0, span, 1), 0.0)


def _pack_111011(t: np.ndarray) -> np.ndarray:
    """[M, 3] values in [0, 1] -> u32 with 11, 10, 11 bits (x in the high bits)."""
    a = np.clip(np.round(t[:, 0] * 2047), 0, 2047).astype(np.uint32)
    b = np.clip(np.round(t[:, 1] * 1023), 0, 1023).astype(np.uint32)
    c = np.clip(np.round(t[:, 2] * 2047), 0, 2047).astype(np.uint32)
    return (a << 21) | (b << 11) | c


def _pack_rotation(q: np.ndarray) -> np.ndarray:
    largest = np.abs(q).argmax(1)
    q = q * np.where(q[np.arange(len(q)), largest] < 0, -1.0, 1.0)[:, None]
    others = np.array([[j for j in range(4) if j != i] for i in range(4)])[largest]  # [N, 3]
    v = np.take_along_axis(q, others, 1)
    bits = np.clip(np.round((v * math.sqrt(2) * 0.5 + 0.5) * 1023), 0, 1023).astype(np.uint32)
    return (largest.astype(np.uint32) << 30) | (bits[:, 0] << 20) | (bits[:, 1] << 10) | bits[:, 2]


def compressed_ply_bytes(scene: GaussianScene) -> bytes:
    """The scene as a PlayCanvas/SuperSplat compressed PLY (see the module notes)."""
    p = _params(scene)
    order = morton_order(p["means"])
    p = {k: v[order] for k, v in p.items()}
    n, k = len(p["means"]), p["sh_rest"].shape[1]
    chunks = math.ceil(n / CHUNK)
    color = 0.5 + SH_C0 * p["sh_dc"]
    chunk_fields = [f"{m}_{a}" for m in ("min", "max") for a in "xyz"] + \
        [f"{m}_scale_{a}" for m in ("min", "max") for a in "xyz"] + [f"{m}_{c}" for m in ("min", "max") for c in "rgb"]
    chunk_rec = np.zeros(chunks, dtype=[(f, "<f4") for f in chunk_fields])
    vert = np.zeros(n, dtype=[(f, "<u4") for f in ("packed_position", "packed_rotation", "packed_scale", "packed_color")])
    for c in range(chunks):
        sl = slice(c * CHUNK, min((c + 1) * CHUNK, n))
        for name, values, fields in (("pos", p["means"][sl], ("x", "y", "z")),
                                     ("scale", p["log_scales"][sl], ("scale_x", "scale_y", "scale_z")),
                                     ("color", color[sl], ("r", "g", "b"))):
            lo, hi = values.min(0), values.max(0)
            for i, f in enumerate(fields):
                chunk_rec[f"min_{f}"][c], chunk_rec[f"max_{f}"][c] = lo[i], hi[i]
            lo32, hi32 = lo.astype(np.float32), hi.astype(np.float32)
            t = _unit(values, lo32, hi32)
            if name == "pos":
                vert["packed_position"][sl] = _pack_111011(t)
            elif name == "scale":
                vert["packed_scale"][sl] = _pack_111011(t)
            else:
                rgba = np.concatenate([t, p["opacity"][sl, None]], 1)
                b = np.clip(np.round(rgba * 255), 0, 255).astype(np.uint32)
                vert["packed_color"][sl] = (b[:, 0] << 24) | (b[:, 1] << 16) | (b[:, 2] << 8) | b[:, 3]
        vert["packed_rotation"][sl] = _pack_rotation(p["quats"][sl])
    header = ["ply", "format binary_little_endian 1.0", "comment written by tiger export",
              f"element chunk {chunks}"] + [f"property float {f}" for f in chunk_fields]
    header += [f"element vertex {n}"] + [f"property uint {f}" for f in vert.dtype.names]
    body = [chunk_rec.tobytes(), vert.tobytes()]
    if k:
        # f_rest_i in INRIA's order: channel-major (all of R's coefficients, then G's, then B's)
        rest = p["sh_rest"].transpose(0, 2, 1).reshape(n, 3 * k)
        header += [f"element sh {n}"] + [f"property uchar f_rest_{i}" for i in range(3 * k)]
        body.append(_u8((rest / 8 + 0.5) * 255).tobytes())
    return ("\n".join(header + ["end_header"]) + "\n").encode("ascii") + b"".join(body)


_WRITERS = {"splat": splat_bytes, "spz": spz_bytes, "ply-compressed": compressed_ply_bytes}


def export_scene(scene: GaussianScene, path: PathLike, fmt: str) -> Path:
    """Write ``scene`` to ``path`` in ``fmt`` (one of :data:`FORMATS`), atomically."""
    if fmt not in _WRITERS:
        raise ValueError(f"tiger.export: format must be one of {FORMATS}, got {fmt!r}")
    data = _WRITERS[fmt](scene)
    path = Path(path)
    with atomic_write(path, "wb") as fh:
        fh.write(data)
    return path


__all__ = ["FORMATS", "SUFFIXES", "compressed_ply_bytes", "export_scene", "morton_order", "splat_bytes",
           "spz_bytes"]
