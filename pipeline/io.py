"""Small, safe file helpers: atomic writes, JSON, images and binary PLY.

Writes go to a temporary file in the same folder and are moved into place with
``os.replace``, so a crash never leaves a half-written file behind: a reader sees
the old file or the new one.
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import tempfile
from pathlib import Path

import numpy as np

from .errors import FormatError

log = logging.getLogger(__name__)

__all__ = [
    "atomic_write_bytes",
    "atomic_write_json",
    "atomic_path",
    "read_json",
    "read_image",
    "write_image",
    "write_ply",
    "read_ply",
]


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike, *, suffix: str | None = None):
    """Yield a temporary path next to ``path``; move it into place on success.

    The temporary file keeps the same extension (OpenCV and Open3D pick the
    format from it). On an exception the temporary file is removed and ``path``
    is left as it was.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    suffix = path.suffix if suffix is None else suffix
    fd, tmp = tempfile.mkstemp(prefix=f".{path.stem}.", suffix=f".tmp{suffix}", dir=path.parent)
    os.close(fd)
    try:
        yield Path(tmp)
        with open(tmp, "rb+") as f:
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        raise


def atomic_write_bytes(path: str | os.PathLike, data: bytes) -> None:
    """Write ``data`` to ``path`` atomically."""
    with atomic_path(path) as tmp:
        tmp.write_bytes(data)


def atomic_write_json(path: str | os.PathLike, obj) -> None:
    """Write ``obj`` as indented JSON to ``path`` atomically."""
    atomic_write_bytes(path, (json.dumps(obj, indent=2, default=_json_default) + "\n").encode())


def _json_default(o):
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, (np.floating, np.integer, np.bool_)):
        return o.item()
    if isinstance(o, Path):
        return str(o)
    raise TypeError(f"not JSON serialisable: {type(o).__name__}")


def read_json(path: str | os.PathLike) -> dict:
    """Read a JSON object, raising :class:`FormatError` naming the file on failure."""
    path = Path(path)
    try:
        text = path.read_text()
    except FileNotFoundError:
        raise FormatError(path, "file not found") from None
    except OSError as e:
        raise FormatError(path, f"cannot read: {e.strerror}") from None
    try:
        obj = json.loads(text)
    except json.JSONDecodeError as e:
        raise FormatError(path, f"not valid JSON (line {e.lineno}, column {e.colno}: {e.msg})") from None
    if not isinstance(obj, dict):
        raise FormatError(path, "expected a JSON object at the top level")
    return obj


def read_image(path: str | os.PathLike) -> np.ndarray:
    """Read an 8- or 16-bit PNG/TIFF as a 2D grey array (uint8 or uint16).

    Colour images are converted to grey (ITU-R 601 luma, as OpenCV does).
    """
    import cv2

    path = Path(path)
    if not path.is_file():
        raise FormatError(path, "image file not found")
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise FormatError(path, "not a readable image (corrupt file or unsupported format)")
    if img.ndim == 3:
        if img.shape[2] == 4:
            img = cv2.cvtColor(img, cv2.COLOR_BGRA2GRAY)
        elif img.shape[2] == 3:
            img = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
        elif img.shape[2] == 1:
            img = img[:, :, 0]
        else:
            raise FormatError(path, f"unsupported channel count {img.shape[2]}")
    if img.dtype not in (np.uint8, np.uint16):
        raise FormatError(path, f"unsupported pixel type {img.dtype} (need 8- or 16-bit)")
    return img


def write_image(path: str | os.PathLike, img: np.ndarray) -> None:
    """Write a grey or BGR uint8/uint16 image atomically (format from the extension)."""
    import cv2

    path = Path(path)
    with atomic_path(path) as tmp:
        if not cv2.imwrite(str(tmp), img):
            raise FormatError(path, "OpenCV could not write the image")


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
_PLY_NAMES.update({"float32": np.dtype("float32"), "float64": np.dtype("float64"), "int8": np.dtype("int8"),
                   "uint8": np.dtype("uint8"), "int16": np.dtype("int16"), "uint16": np.dtype("uint16"),
                   "int32": np.dtype("int32"), "uint32": np.dtype("uint32")})


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
