"""TODO docstring (ringscan.pipeline.formats.ply, split from ringscan.pipeline.formats.atomic)."""

from __future__ import annotations

import logging
import os
from pathlib import Path

import numpy as np

from ringscan.pipeline.formats.atomic import atomic_path
from ringscan.pipeline.formats.errors import FormatError

log = logging.getLogger(__name__)


_PLY_TYPES = {
    np.dtype("float32"): "float",
    np.dtype("float64"): "double",
    np.dtype("int32"): "int",
    np.dtype("uint32"): "uint",
    np.dtype("int16"): "short",
    np.dtype("uint16"): "ushort",
    np.dtype("int8"): "char",
    np.dtype("uint8"): "uchar",
}


_PLY_NAMES = {v: k for k, v in _PLY_TYPES.items()}


def write_ply(path: str | os.PathLike, fields: dict[str, np.ndarray], *, comments: list[str] | None = None) -> None:
    """Write a binary little-endian PLY point cloud atomically.

    Args:
        path: output file.
        fields: vertex properties in order, each a 1D array of one length, e.g.
            ``{"x": ..., "y": ..., "z": ..., "nx": ..., "ring": ..., "view": ...}``.
        comments: header comment lines.
    """
    n = None
    cols = []
    for name, arr in fields.items():
        arr = np.asarray(arr)
        if arr.ndim != 1:
            raise ValueError(f"PLY field {name!r} must be 1D, got shape {arr.shape}")
        if n is None:
            n = arr.shape[0]
        elif arr.shape[0] != n:
            raise ValueError(f"PLY field {name!r} has {arr.shape[0]} values, expected {n}")
        if arr.dtype not in _PLY_TYPES:
            arr = arr.astype(np.float32 if arr.dtype.kind == "f" else np.int32)
        cols.append((name, arr))
    n = n or 0
    header = ["ply", "format binary_little_endian 1.0"]
    header += [f"comment {c}" for c in (comments or [])]
    header.append(f"element vertex {n}")
    header += [f"property {_PLY_TYPES[a.dtype]} {name}" for name, a in cols]
    header.append("end_header")
    rec = np.empty(n, dtype=[(name, a.dtype.newbyteorder("<")) for name, a in cols])
    for name, a in cols:
        rec[name] = a
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as f:
            f.write(("\n".join(header) + "\n").encode("ascii"))
            f.write(rec.tobytes())


def read_ply(path: str | os.PathLike) -> dict[str, np.ndarray]:
    """Read the vertex element of a binary little-endian PLY written by :func:`write_ply`.

    Returns a dict of 1D arrays by property name. Faces, if any, are ignored (use
    Open3D for meshes).
    """
    path = Path(path)
    try:
        data = path.read_bytes()
    except FileNotFoundError:
        raise FormatError(path, "file not found") from None
    end = data.find(b"end_header\n")
    if not data.startswith(b"ply") or end < 0:
        raise FormatError(path, "not a PLY file")
    lines = data[:end].decode("ascii", "replace").splitlines()
    if "format binary_little_endian 1.0" not in lines:
        raise FormatError(path, "only binary little-endian PLY is supported here; use Open3D for others")
    props, n, in_vertex = [], 0, False
    for ln in lines:
        parts = ln.split()
        if parts[:2] == ["element", "vertex"]:
            n, in_vertex = int(parts[2]), True
        elif parts[:1] == ["element"]:
            in_vertex = False
        elif parts[:1] == ["property"] and in_vertex:
            if parts[1] == "list" or parts[1] not in _PLY_NAMES:
                raise FormatError(path, f"unsupported vertex property {' '.join(parts[1:])}")
            props.append((parts[2], _PLY_NAMES[parts[1]].newbyteorder("<")))
    dt = np.dtype(props)
    body = data[end + len(b"end_header\n"):]
    if len(body) < n * dt.itemsize:
        raise FormatError(path, f"truncated: header says {n} vertices, file holds {len(body) // max(dt.itemsize, 1)}")
    rec = np.frombuffer(body, dtype=dt, count=n)
    return {name: rec[name].astype(rec[name].dtype.newbyteorder("=")) for name, _ in props}
