"""An independent minimal PLY writer for the tests (written from the PLY spec and the
INRIA 3DGS property list, sharing no code with tiger.scene.ply)."""
from __future__ import annotations

import struct
from pathlib import Path

import numpy as np


def inria_names(sh_degree: int, normals: bool = True, lang: int = 0) -> list:
    k = (sh_degree + 1) ** 2 - 1
    names = ["x", "y", "z"] + (["nx", "ny", "nz"] if normals else [])
    names += ["f_dc_0", "f_dc_1", "f_dc_2"] + [f"f_rest_{i}" for i in range(3 * k)]
    names += ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    return names + [f"lang_{i}" for i in range(lang)]


def random_columns(n: int, sh_degree: int, normals: bool = True, lang: int = 0, seed: int = 0) -> dict:
    """name -> float32 column of plausible 3DGS values."""
    rng = np.random.default_rng(seed)
    return {name: rng.normal(size=n).astype(np.float32) for name in inria_names(sh_degree, normals, lang)}


def write_ply(path: Path, columns: dict, fmt: str = "binary_little_endian", types: dict | None = None,
              comments: tuple = (), extra_element: bool = False) -> None:
    """Write one ``vertex`` element with ``columns`` (ordered dict name -> array) in ``fmt``
    (``ascii``, ``binary_little_endian``, ``binary_big_endian``); ``types`` maps names to
    PLY types (default float). ``extra_element`` appends a face element with lists."""
    types = types or {}
    names = list(columns)
    n = len(next(iter(columns.values())))
    lines = ["ply", f"format {fmt} 1.0"] + [f"comment {c}" for c in comments] + [f"element vertex {n}"]
    lines += [f"property {types.get(k, 'float')} {k}" for k in names]
    if extra_element:
        lines += ["element face 2", "property list uchar int vertex_indices"]
    lines.append("end_header")
    head = ("\n".join(lines) + "\n").encode("ascii")
    codes = {"float": "f", "double": "d", "uchar": "B", "int": "i", "short": "h"}
    if fmt == "ascii":
        rows = []
        for i in range(n):
            rows.append(" ".join(repr(float(columns[k][i])) if types.get(k, "float") in ("float", "double")
                                 else str(int(columns[k][i])) for k in names))
        body = ("\n".join(rows) + "\n").encode("ascii")
        if extra_element:
            body += b"3 0 1 2\n3 1 2 0\n"
    else:
        e = "<" if fmt == "binary_little_endian" else ">"
        rowfmt = e + "".join(codes[types.get(k, "float")] for k in names)
        body = b"".join(struct.pack(rowfmt, *[columns[k][i].item() for k in names]) for i in range(n))
        if extra_element:
            body += struct.pack(e + "Biii", 3, 0, 1, 2) + struct.pack(e + "Biii", 3, 1, 2, 0)
    Path(path).write_bytes(head + body)
