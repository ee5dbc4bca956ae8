"""3DGS PLY files in the INRIA layout (what every 3DGS viewer reads).

Written: binary little endian, one ``vertex`` element of float32 properties in INRIA's
order ``x y z nx ny nz f_dc_0..2 f_rest_0..(3K-1) opacity scale_0..2 rot_0..3`` (normals
zero), then ``lang_0..lang_{D-1}`` when the scene has language features. ``f_rest`` is
channel-major (all K coefficients of red, then green, then blue), as INRIA writes it.
Scene metadata travels in one ``comment tiger_metadata <json>`` header line; the
language PCA basis/mean in a sidecar ``<name>.lang_pca.npz``.

Read: ``ascii``, ``binary_little_endian`` and ``binary_big_endian``; any scalar type per
property; any property order; normals and higher SH bands optional; other elements
(faces, camera blocks) skipped. Bad files raise :class:`SceneFormatError` naming the
file and the property.
"""
from __future__ import annotations

import json
import logging
import os
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Optional, Union

import numpy as np
import torch

from tiger.utils.io import atomic_write

from .errors import SceneFormatError
from .sh import num_sh_bases, sh_degree_from_rest

#: The tensors of a scene by name, plus "metadata" (``GaussianScene.state_dict`` form).
SceneState = dict[str, Union[torch.Tensor, dict, None]]

log = logging.getLogger(__name__)
PathLike = Union[str, os.PathLike]

_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1",
    "short": "i2", "int16": "i2", "ushort": "u2", "uint16": "u2",
    "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4", "double": "f8", "float64": "f8",
}
_MAX_HEADER = 1 << 24  # a header (with metadata comments) larger than 16 MiB is not a PLY
_META_PREFIX = "tiger_metadata "


@dataclass
class _Property:
    name: str
    dtype: str                   # numpy type code without byte order
    count_dtype: Optional[str] = None  # set for list properties


@dataclass
class _Element:
    name: str
    count: int
    props: list


@dataclass
class PlyHeader:
    format: str
    elements: list
    comments: list
    data_offset: int


def lang_pca_path(path: PathLike) -> Path:
    """The sidecar holding a scene's language PCA basis/mean next to ``path``."""
    p = Path(path)
    return p.with_name(p.stem + ".lang_pca.npz")


# ---------------------------------------------------------------------------------------
# Header
# ---------------------------------------------------------------------------------------
def parse_header(data: bytes, path: PathLike) -> PlyHeader:
    """Parse the PLY header at the start of ``data``."""
    if not data.startswith(b"ply"):
        raise SceneFormatError(path, "not a PLY file (it does not start with 'ply')")
    end = re.search(rb"end_header[ \t]*\r?\n", data[:_MAX_HEADER])
    if end is None:
        raise SceneFormatError(path, "PLY header has no 'end_header' line (truncated or not a PLY)")
    try:
        text = data[: end.start()].decode("ascii")
    except UnicodeDecodeError as exc:
        raise SceneFormatError(path, f"PLY header contains non-ASCII bytes at offset {exc.start}") from None
    fmt: Optional[str] = None
    elements: list = []
    comments: list = []
    for lineno, raw in enumerate(text.splitlines()[1:], start=2):
        line = raw.strip()
        if not line:
            continue
        tok = line.split()
        key = tok[0]
        if key == "format":
            if len(tok) != 3 or tok[1] not in ("ascii", "binary_little_endian", "binary_big_endian"):
                raise SceneFormatError(path, f"header line {lineno}: unsupported format '{line}'", "format")
            if tok[2] not in ("1.0", "1"):
                raise SceneFormatError(path, f"header line {lineno}: unsupported PLY version {tok[2]}", "format")
            fmt = tok[1]
        elif key in ("comment", "obj_info"):
            comments.append(raw.split(None, 1)[1] if len(raw.split(None, 1)) > 1 else "")
        elif key == "element":
            if len(tok) != 3 or not tok[2].isdigit():
                raise SceneFormatError(path, f"header line {lineno}: malformed element line '{line}'", "element")
            elements.append(_Element(tok[1], int(tok[2]), []))
        elif key == "property":
            if not elements:
                raise SceneFormatError(path, f"header line {lineno}: property before any element", "property")
            if len(tok) == 3 and tok[1] in _TYPES:
                elements[-1].props.append(_Property(tok[2], _TYPES[tok[1]]))
            elif len(tok) == 5 and tok[1] == "list" and tok[2] in _TYPES and tok[3] in _TYPES:
                if tok[2].startswith(("float", "double")):
                    raise SceneFormatError(path, f"header line {lineno}: list count type must be an integer",
                                           tok[4])
                elements[-1].props.append(_Property(tok[4], _TYPES[tok[3]], _TYPES[tok[2]]))
            else:
                raise SceneFormatError(path, f"header line {lineno}: malformed or unknown property type '{line}'",
                                       tok[-1] if len(tok) > 1 else "property")
        else:
            raise SceneFormatError(path, f"header line {lineno}: unknown keyword '{key}'")
    if fmt is None:
        raise SceneFormatError(path, "PLY header has no 'format' line", "format")
    for el in elements:
        names = [p.name for p in el.props]
        dup = {n for n in names if names.count(n) > 1}
        if dup:
            raise SceneFormatError(path, f"element '{el.name}' repeats properties {sorted(dup)}", sorted(dup)[0])
    return PlyHeader(fmt, elements, comments, end.end())


# ---------------------------------------------------------------------------------------
# Element data
# ---------------------------------------------------------------------------------------
def _read_binary(data: bytes, offset: int, el: _Element, order: str, path: PathLike):
    """Read element ``el`` at ``offset``; returns (dict name -> array, new offset)."""
    if all(p.count_dtype is None for p in el.props):
        dt = np.dtype([(p.name, order + p.dtype) for p in el.props])
        need = el.count * dt.itemsize
        have = len(data) - offset
        if need > have:
            raise SceneFormatError(
                path, f"truncated: element '{el.name}' needs {el.count} x {dt.itemsize} = {need} bytes "
                      f"but only {have} remain", el.name)
        arr = np.frombuffer(data, dtype=dt, count=el.count, offset=offset)
        return {p.name: arr[p.name] for p in el.props}, offset + need
    # Lists (faces): walk row by row; only needed to skip such elements.
    out: dict = {p.name: [] for p in el.props}
    pos = offset
    for row in range(el.count):
        for p in el.props:
            if p.count_dtype is None:
                size = np.dtype(p.dtype).itemsize
                if pos + size > len(data):
                    raise SceneFormatError(path, f"truncated in row {row} of element '{el.name}'", p.name)
                out[p.name].append(np.frombuffer(data, order + p.dtype, 1, pos)[0])
                pos += size
            else:
                csize = np.dtype(p.count_dtype).itemsize
                if pos + csize > len(data):
                    raise SceneFormatError(path, f"truncated in row {row} of element '{el.name}'", p.name)
                n = int(np.frombuffer(data, order + p.count_dtype, 1, pos)[0])
                pos += csize
                size = np.dtype(p.dtype).itemsize
                if n < 0 or pos + n * size > len(data):
                    raise SceneFormatError(path, f"truncated or bad list length {n} in row {row} of "
                                                 f"element '{el.name}'", p.name)
                out[p.name].append(np.frombuffer(data, order + p.dtype, n, pos))
                pos += n * size
    return out, pos


def _read_ascii(lines: list, start: int, el: _Element, path: PathLike):
    """Read element ``el`` from ``lines[start:]``; returns (dict, next line index)."""
    if start + el.count > len(lines):
        raise SceneFormatError(path, f"truncated: element '{el.name}' has {el.count} rows but only "
                                     f"{len(lines) - start} data lines remain", el.name)
    rows = lines[start:start + el.count]
    if all(p.count_dtype is None for p in el.props):
        n = len(el.props)
        try:
            flat = np.array(" ".join(rows).split(), dtype=np.float64)
        except ValueError:
            r, fld, msg = _first_bad_ascii_row(rows, el.props)
            raise SceneFormatError(path, f"row {r} of element '{el.name}': {msg}", fld) from None
        if flat.size != n * el.count:
            r, fld, msg = _first_bad_ascii_row(rows, el.props)
            raise SceneFormatError(path, f"row {r} of element '{el.name}': {msg}", fld)
        flat = flat.reshape(el.count, n)
        out = {}
        for i, p in enumerate(el.props):
            col = flat[:, i]
            if p.dtype[0] in "iu" and not np.all(col == np.round(col)):
                raise SceneFormatError(path, f"non-integer value in integer property of element '{el.name}'",
                                       p.name)
            out[p.name] = col.astype(p.dtype)
        return out, start + el.count
    out = {p.name: [] for p in el.props}  # lists: parse per row (only to skip them)
    for r, row in enumerate(rows):
        tok = row.split()
        i = 0
        try:
            for p in el.props:
                if p.count_dtype is None:
                    out[p.name].append(float(tok[i]))
                    i += 1
                else:
                    k = int(tok[i])
                    if k < 0:
                        raise ValueError
                    out[p.name].append([float(t) for t in tok[i + 1:i + 1 + k]])
                    if len(out[p.name][-1]) != k:
                        raise IndexError
                    i += 1 + k
        except (ValueError, IndexError):
            raise SceneFormatError(path, f"malformed row {r} of element '{el.name}'", el.name) from None
    return out, start + el.count


def _first_bad_ascii_row(rows: list, props: list) -> tuple:
    """(row, field, message) of the first malformed row of an ASCII element."""
    for r, row in enumerate(rows):
        tok = row.split()
        for i, t in enumerate(tok):
            try:
                float(t)
            except ValueError:
                name = props[i].name if i < len(props) else f"value {i}"
                return r, name, f"'{t[:20]}' is not a number"
        if len(tok) != len(props):
            return r, f"row {r}", f"{len(tok)} values instead of {len(props)}"
    return -1, "data", "malformed"


def read_ply_elements(path: PathLike, stop_after: Optional[str] = None) -> tuple:
    """Parse any PLY file: returns (header, {element name: {property: numpy array}}).

    ``stop_after``: an element name after which the rest of the file is not read.
    """
    path = Path(path)
    try:
        data = path.read_bytes()
    except FileNotFoundError:
        raise SceneFormatError(path, "file not found") from None
    except IsADirectoryError:
        raise SceneFormatError(path, "is a directory, not a PLY file") from None
    hdr = parse_header(data, path)
    out: dict = {}
    if hdr.format == "ascii":
        try:
            body = data[hdr.data_offset:].decode("ascii")
        except UnicodeDecodeError as exc:
            raise SceneFormatError(path, f"ASCII PLY body has a non-ASCII byte at offset "
                                         f"{hdr.data_offset + exc.start}") from None
        lines = [ln for ln in body.splitlines() if ln.strip()]
        pos = 0
        for el in hdr.elements:
            out[el.name], pos = _read_ascii(lines, pos, el, path)
            if el.name == stop_after:
                break
    else:
        order = "<" if hdr.format == "binary_little_endian" else ">"
        pos = hdr.data_offset
        for el in hdr.elements:
            out[el.name], pos = _read_binary(data, pos, el, order, path)
            if el.name == stop_after:
                break
    return hdr, out


# ---------------------------------------------------------------------------------------
# Gaussian scenes
# ---------------------------------------------------------------------------------------
def _indexed(props: dict, prefix: str) -> list:
    """Names ``prefix0..prefixN`` present in ``props``, sorted by index; raises when the
    indices are not contiguous from 0."""
    found = sorted((int(m.group(1)), n) for n in props if (m := re.fullmatch(re.escape(prefix) + r"(\d+)", n)))
    for expect, (i, _) in enumerate(found):
        if i != expect:  # the first gap (never materialise range(max index): it can be huge)
            raise KeyError(f"{prefix}{expect}")
    return [n for _, n in found]


def read_ply_state(path: PathLike, allow_nonfinite: bool = False,
                   dtype: torch.dtype = torch.float32) -> SceneState:
    """Read a 3DGS PLY (INRIA, gsplat, nerfstudio, SuperSplat... exports) into a scene's tensors
    (``GaussianScene.load_ply`` / :func:`tiger.scene.read_ply` build the scene from them).

    Args:
        path: the ``.ply`` file.
        allow_nonfinite: keep NaN/Inf values instead of raising.
        dtype: floating dtype of the tensors.
    Returns:
        ``means`` [N, 3], ``log_scales`` [N, 3], ``quats`` [N, 4], ``opacity_logits`` [N],
        ``sh_dc`` [N, 3], ``sh_rest`` [N, K, 3], ``lang`` [N, D] when ``lang_*`` properties
        exist (else None), ``lang_pca_basis`` [F, D] / ``lang_pca_mean`` [F] from the sidecar
        ``<stem>.lang_pca.npz`` when present, ``metadata`` from the ``tiger_metadata`` comment.
    Raises:
        SceneFormatError naming the file and the missing or malformed property.
    """
    path = Path(path)
    hdr, elements = read_ply_elements(path, stop_after="vertex")
    if "vertex" not in elements:
        raise SceneFormatError(path, "no 'vertex' element: not a Gaussian splat PLY", "vertex")
    v = elements["vertex"]
    vprops = next(e for e in hdr.elements if e.name == "vertex").props
    lists = [p.name for p in vprops if p.count_dtype is not None]
    if lists:
        raise SceneFormatError(path, "list properties are not allowed in the vertex element", lists[0])

    def get(names: list) -> torch.Tensor:
        for n in names:
            if n not in v:
                raise SceneFormatError(path, "required 3DGS property is missing (not a Gaussian splat PLY?)", n)
        arr = np.stack([np.asarray(v[n], dtype=np.float64 if dtype == torch.float64 else np.float32)
                        for n in names], axis=1) if names else np.zeros((len(next(iter(v.values()))), 0))
        if not allow_nonfinite:
            bad = ~np.isfinite(arr)
            if bad.any():
                r, c = np.argwhere(bad)[0]
                raise SceneFormatError(path, f"non-finite value {arr[r, c]} in vertex {r}", names[c])
        return torch.from_numpy(np.ascontiguousarray(arr)).to(dtype)

    try:
        rest_names = _indexed(v, "f_rest_")
        lang_names = _indexed(v, "lang_")
    except KeyError as exc:
        raise SceneFormatError(path, "indexed properties are not contiguous from 0", exc.args[0]) from None
    if len(rest_names) % 3:
        raise SceneFormatError(path, f"{len(rest_names)} f_rest properties is not a multiple of 3", "f_rest_0")
    try:
        sh_degree_from_rest(len(rest_names) // 3)
    except ValueError:
        raise SceneFormatError(path, f"{len(rest_names)} f_rest properties match no SH degree 0..3 "
                                     "(expected 0, 9, 24 or 45)", "f_rest_0") from None

    means = get(["x", "y", "z"])
    N = means.shape[0]
    sh_dc = get(["f_dc_0", "f_dc_1", "f_dc_2"])
    K = len(rest_names) // 3
    sh_rest = get(rest_names).reshape(N, 3, K).transpose(1, 2).contiguous()
    opacity = get(["opacity"])[:, 0].contiguous()
    log_scales = get(["scale_0", "scale_1", "scale_2"])
    quats = get(["rot_0", "rot_1", "rot_2", "rot_3"])
    lang = get(lang_names) if lang_names else None

    metadata: dict = {}
    for c in hdr.comments:
        if c.startswith(_META_PREFIX):
            try:
                metadata = json.loads(c[len(_META_PREFIX):])
            except json.JSONDecodeError as exc:
                raise SceneFormatError(path, f"metadata comment is not valid JSON ({exc.msg})",
                                       "comment tiger_metadata") from None
            if not isinstance(metadata, dict):
                raise SceneFormatError(path, "metadata comment must hold a JSON object", "comment tiger_metadata")
    basis = mean = None
    side = lang_pca_path(path)
    if side.exists():
        basis, mean = _read_pca(side, dtype)
        if lang is not None and basis.shape[1] != lang.shape[1]:
            raise SceneFormatError(side, f"basis maps to {basis.shape[1]} dims but the PLY has "
                                         f"{lang.shape[1]} lang_* properties", "basis")
    return {"means": means, "log_scales": log_scales, "quats": quats, "opacity_logits": opacity,
            "sh_dc": sh_dc, "sh_rest": sh_rest, "lang": lang, "lang_pca_basis": basis,
            "lang_pca_mean": mean, "metadata": metadata}


def _read_pca(path: Path, dtype: torch.dtype) -> tuple:
    try:
        with np.load(path, allow_pickle=False) as z:
            basis, mean = z["basis"], z["mean"]
    except KeyError as exc:
        raise SceneFormatError(path, "language PCA sidecar lacks an array", str(exc.args[0])) from None
    except Exception as exc:  # zipfile/numpy raise many types on corrupt input
        raise SceneFormatError(path, f"cannot read the language PCA sidecar ({type(exc).__name__}: {exc})") from None
    if basis.ndim != 2 or mean.shape != (basis.shape[0],):
        raise SceneFormatError(path, f"basis [F, D] and mean [F] disagree: {basis.shape} vs {mean.shape}", "basis")
    return torch.from_numpy(basis).to(dtype), torch.from_numpy(mean).to(dtype)


def ply_property_names(sh_degree: int, lang_dim: int = 0) -> list:
    """Vertex property names of a saved scene, in INRIA's order (then ``lang_*``)."""
    K = num_sh_bases(sh_degree) - 1
    return (["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
            + [f"f_rest_{i}" for i in range(3 * K)] + ["opacity", "scale_0", "scale_1", "scale_2"]
            + ["rot_0", "rot_1", "rot_2", "rot_3"] + [f"lang_{i}" for i in range(lang_dim)])


def write_ply_state(state: SceneState, path: PathLike, include_language: bool = True,
                    include_metadata: bool = True) -> None:
    """Write a scene's tensors (as :func:`read_ply_state` returns them, float32 on the CPU) as an
    INRIA-layout binary PLY, atomically (``GaussianScene.save_ply`` converts and calls this).

    Args:
        state: ``means`` [N, 3], ``log_scales`` [N, 3], ``quats`` [N, 4], ``opacity_logits`` [N],
            ``sh_dc`` [N, 3], ``sh_rest`` [N, K, 3], ``lang`` [N, D] or None, ``lang_pca_basis``
            / ``lang_pca_mean`` or None, ``metadata`` dict.
        path: destination ``.ply``.
        include_language: also write ``lang_*`` (and the PCA sidecar) when present; turn
            off for viewers that require INRIA's exact vertex size (SIBR).
        include_metadata: write the ``tiger_metadata`` comment.
    """
    path = Path(path)
    means, sh_rest = state["means"], state["sh_rest"]
    N, K = means.shape[0], sh_rest.shape[1]
    lang = state["lang"] if include_language else None
    names = ply_property_names(sh_degree_from_rest(K), 0 if lang is None else lang.shape[1])
    cols = [means, torch.zeros_like(means), state["sh_dc"], sh_rest.transpose(1, 2).reshape(N, 3 * K),
            state["opacity_logits"][:, None], state["log_scales"], state["quats"]]
    if lang is not None:
        cols.append(lang)
    table = torch.cat(cols, 1).contiguous().numpy()
    assert table.shape[1] == len(names)
    rec = np.empty(N, dtype=np.dtype([(n, "<f4") for n in names]))
    rec.view("<f4").reshape(N, len(names))[:] = table
    header = ["ply", "format binary_little_endian 1.0"]
    if include_metadata and state["metadata"]:
        meta = json.dumps(state["metadata"], separators=(",", ":"), ensure_ascii=True)
        header.append(f"comment {_META_PREFIX}{meta}")
    header.append(f"element vertex {N}")
    header += [f"property float {n}" for n in names]
    header.append("end_header")
    with atomic_write(path, "wb") as fh:
        fh.write(("\n".join(header) + "\n").encode("ascii"))
        fh.write(rec.tobytes())
    side = lang_pca_path(path)
    if lang is not None and state["lang_pca_basis"] is not None:
        with atomic_write(side, "wb") as fh:
            np.savez(fh, basis=state["lang_pca_basis"].numpy(), mean=state["lang_pca_mean"].numpy())
    elif side.exists():
        side.unlink()  # a stale basis from an earlier save would be mis-attributed
