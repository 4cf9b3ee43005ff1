"""The packed frame store: a view's frames as one Zarr v3 array (docs/formats.md).

::

    view_000/frames.zarr/zarr.json      the array's metadata (shape, dtype, codecs, frame names)
    view_000/frames.zarr/c/<i>/0/0      frame i: Blosc (zstd 5, bit-shuffle) + CRC32C

One array of shape (n_frames, H, W), uint8 or uint16, one chunk per frame, each
chunk compressed losslessly with Blosc (zstd level 5 after a bit-shuffle) and
ending in its CRC32C (Zarr's ``crc32c`` codec). Any Zarr v3 reader opens it
(zarr-python, tensorstore, zarrs ...); the frame names are the array attribute
``ringscan.frames``. ringscan reads and writes the chunks itself: the reader checks
every chunk's checksum and refuses a missing chunk (which a generic Zarr reader
would silently fill with zeros), and decodes straight into the output array.

Stores are written whole into a temporary folder and renamed into place
(:func:`write_store`), or created empty and filled frame by frame
(:func:`create_store`, :func:`write_frame`; each chunk written atomically), so a
killed writer leaves either nothing, or a store whose written frames are whole.
A scan on object storage is staged into a local folder first
(:mod:`~ringscan.pipeline.formats.storage`: zarr.json, then the chunks of the views
computed), so this module reads and writes local paths only.

Why not through zarr-python (issue 36 item 5: a library's reader unless it is more than
1.2x slower on a view). zarr-python 3.1.6 (declared in the ``test`` extra only, not a
runtime dependency) reads these stores bit-exactly and writes the same layout
(tests/pipeline/formats/test_frame_store.py), but it reads a view 1.3x slower.
``python benchmarks/frame_store.py --rounds 15`` (one 1280x1024 8-bit view, best of 15
interleaved rounds, the 2-core development machine shared with other jobs at load
average 2-5), zarr-python's time over this reader's, two runs:

- 38 simulated frames: one thread 1.26x (64.4 against 51.2 ms) and 1.49x (72.5 / 48.7);
  behind ringscan's checks 1.28x, 1.47x; 2 cores 1.35x (66.1 / 49.2), 2.06x (74.6 / 36.3).
- 28 frames of shared/data/procam/capture_1: one thread 1.27x (59.7 / 46.8 ms) and 1.27x
  (60.8 / 47.9); behind the checks 1.32x, 1.28x; 2 cores 1.47x (51.8 / 35.2), 1.33x.

Three earlier runs of the same reads: one thread 1.23-1.36x, behind the checks
1.29-1.36x, 2 cores 1.20-1.63x; one at load average ~7 measured 1.09-1.11x, the
contention hiding the difference. "Behind the checks": after :func:`open_store` and
:func:`check_chunk_files`, which a read through zarr-python would need first. Where the
time goes: zarr-python reads each chunk file into new bytes, decodes it into a new
array and copies that into the output; this reader reuses one buffer per thread and
decodes straight into the output stack. ringscan's checks would also stay around it:
zarr-python fills a missing chunk with zeros, its checksum error (``ValueError: Stored
and computed checksum do not match``) names no chunk, and its concurrency is a
process-wide setting (``async.concurrency``), not a call's own ``threads``.

The writer stays too. zarr-python writes byte-identical chunk files (both encode with
numcodecs' Blosc; the benchmark compares them) in about the same time (the runs above:
667-722 against 637-757 ms for the 38 frames, 705-904 against 686-833 ms for the 28,
ringscan's including its read-back), but its local store writes each chunk through
``<key>.<uuid>.partial`` without fsync and removes that file only on an ``Exception``:
a killed (or interrupted) writer leaves it behind, and nothing tells a live writer's
file from a dead one's. ringscan's chunks go through :mod:`~ringscan.pipeline.formats.atomic`
(fsync, temporaries named ``.<name>.<pid>-<hex>.tmp`` that
:func:`remove_stale_chunk_temporaries` removes when a capture resumes), and a whole
store is read back and compared before its rename.
"""

from __future__ import annotations

import os
import re
import secrets
import shutil
import stat
import threading
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ringscan.pipeline.formats.atomic import _process_alive, atomic_write_bytes, atomic_write_json, read_json
from ringscan.pipeline.formats.errors import FormatError
from ringscan.pipeline.formats.limits import MAX_IMAGE_PIXELS, mode_kind

STORE_FORMAT = "ringscan.frames/1"
"""The ``ringscan.format`` attribute of a store's zarr.json."""
STORE_NAME = "frames.zarr"
"""The store's folder name inside a view folder."""
BLOSC = {"cname": "zstd", "clevel": 5, "shuffle": "bitshuffle", "blocksize": 0}
"""The Blosc settings every frame is written with: zstd level 5 after a bit-shuffle, Blosc's own block size.

Chosen by measurement (``benchmarks/frame_store.py``; docs/formats.md has the table): the
only codec family within 1.2x the PNG's size on the real captures as well as on simulated
frames (zstd 5: 1.08x simulated, 1.14-1.19x on shared/data/procam's three captures). LZ4HC
level 9 decodes 1.7-3x faster but is 1.19-1.24x the PNG on the real captures (LZ4 and
BloscLZ more still); zstd 1-3 are larger and no faster to decode; zstd 7-9 are 2-5 % smaller,
decode at the same speed and encode 4-30x slower; a block size of 64 KiB-1 MiB changed
little. Decoding the frames is ~90 % of reading a store (reading the files and their
CRC32C another ~2 ms a view). The reader takes any Blosc codec numcodecs decodes (the
codec is in each chunk's header), so stores written with other settings still read."""
MAX_FRAMES = 4096
"""The most frames a store may hold (a bound on bad input)."""
MAX_SIDE = 65536
"""The largest frame side (the rig's bound on camera sizes)."""

_TMP_DIR_RE = re.compile(r"^\..+\.(?P<pid>\d+)-[0-9a-f]{8}\.tmp$")
_DTYPES = {"uint8": np.uint8, "uint16": np.uint16}

__all__ = ["STORE_FORMAT", "STORE_NAME", "BLOSC", "StoreInfo", "open_store", "read_store", "write_store",
           "create_store", "write_frame", "missing_frames", "check_chunk_files", "is_store", "remove_stale_stores",
           "remove_stale_chunk_temporaries"]


@dataclass(frozen=True)
class StoreInfo:
    """A store's checked metadata."""

    path: Path
    """The store folder."""
    names: tuple[str, ...]
    """Frame names in store order (index i is chunk ``c/i/0/0``)."""
    height: int
    """Frame height in pixels."""
    width: int
    """Frame width in pixels."""
    dtype: np.dtype
    """uint8 or uint16."""

    def chunk_path(self, index: int) -> Path:
        return self.path / "c" / str(index) / "0" / "0"

    def index(self, name: str) -> int:
        return self.names.index(name)


def is_store(path: str | os.PathLike) -> bool:
    """Whether ``path`` is a folder with a zarr.json (a store, checked or not)."""
    return (Path(path) / "zarr.json").is_file()


def _codecs(dtype: np.dtype) -> list[dict]:
    return [{"name": "bytes", "configuration": {"endian": "little"}},
            {"name": "blosc", "configuration": {**BLOSC, "typesize": int(np.dtype(dtype).itemsize)}},
            {"name": "crc32c"}]


def _metadata(names: Sequence[str], height: int, width: int, dtype) -> dict:
    return {"zarr_format": 3, "node_type": "array", "shape": [len(names), int(height), int(width)],
            "data_type": np.dtype(dtype).name,
            "chunk_grid": {"name": "regular", "configuration": {"chunk_shape": [1, int(height), int(width)]}},
            "chunk_key_encoding": {"name": "default", "configuration": {"separator": "/"}},
            "fill_value": 0, "codecs": _codecs(dtype), "dimension_names": ["frame", "y", "x"],
            "attributes": {"ringscan": {"format": STORE_FORMAT, "frames": list(names)}}}


def _check_new(names: Sequence[str], height: int, width: int, dtype) -> np.dtype:
    dt = np.dtype(dtype)
    if dt.name not in _DTYPES:
        raise ValueError(f"frame store: frames must be uint8 or uint16, not {dt}")
    if not names or len(set(names)) != len(names) or len(names) > MAX_FRAMES:
        raise ValueError(f"frame store: need 1 to {MAX_FRAMES} distinct frame names, got {list(names)!r}")
    if not (0 < height <= MAX_SIDE and 0 < width <= MAX_SIDE):
        raise ValueError(f"frame store: frame size {width}x{height} out of range")
    return dt


def open_store(path: str | os.PathLike) -> StoreInfo:
    """Read and check a store's zarr.json.

    Raises:
        FormatError: naming the zarr.json for a missing file, a layout other than
            the one described in the module docstring, or bad frame names.
    """
    path = Path(path)
    meta = path / "zarr.json"
    if not os.path.lexists(meta):
        raise FormatError(meta, "frame store metadata not found")
    # a regular file of at most 1 MiB (a FIFO would block, /dev/zero never end); JSON nested too deeply
    # for the parser is refused as not valid JSON
    d = read_json(meta, max_bytes=1 << 20)
    if d.get("zarr_format") != 3 or d.get("node_type") != "array":
        raise FormatError(meta, "not a Zarr v3 array")
    shape = d.get("shape")
    if (not isinstance(shape, list) or len(shape) != 3
            or not all(isinstance(s, int) and not isinstance(s, bool) for s in shape)):
        raise FormatError(meta, f"shape: expected [frames, height, width], got {shape!r}")
    n, h, w = shape
    if not (0 < n <= MAX_FRAMES and 0 < h <= MAX_SIDE and 0 < w <= MAX_SIDE):
        raise FormatError(meta, f"shape: {shape} out of range")
    if h * w > MAX_IMAGE_PIXELS:  # as an image file's header: refused before a frame is decoded
        raise FormatError(meta, f"frames are {w}x{h} ({w * h / 1e6:.0f} megapixels): larger than ringscan reads "
                                f"(at most {MAX_SIDE} px a side, {MAX_IMAGE_PIXELS / 1e6:.0f} megapixels)")
    dt = d.get("data_type")
    if dt not in _DTYPES:
        raise FormatError(meta, f"data_type: expected uint8 or uint16, got {dt!r}")
    grid = d.get("chunk_grid")
    if grid != {"name": "regular", "configuration": {"chunk_shape": [1, h, w]}}:
        raise FormatError(meta, f"chunk_grid: expected one chunk per frame ([1, {h}, {w}]), got {grid!r}")
    keys = d.get("chunk_key_encoding")
    if keys != {"name": "default", "configuration": {"separator": "/"}}:
        raise FormatError(meta, f"chunk_key_encoding: expected the default with '/', got {keys!r}")
    codecs = d.get("codecs")
    names_ok = isinstance(codecs, list) and [c.get("name") if isinstance(c, dict) else None for c in codecs]
    if names_ok != ["bytes", "blosc", "crc32c"]:
        raise FormatError(meta, "codecs: expected bytes, blosc, crc32c (ringscan reads only stores laid out "
                                f"as it writes them), got {names_ok or codecs!r}")
    endian = (codecs[0].get("configuration") or {}).get("endian", "little")
    if endian != "little" and dt != "uint8":
        raise FormatError(meta, f"codecs: bytes codec with {endian!r} byte order (need little)")
    attrs = (d.get("attributes") or {}).get("ringscan") if isinstance(d.get("attributes"), dict) else None
    if not isinstance(attrs, dict) or attrs.get("format") != STORE_FORMAT:
        raise FormatError(meta, f"attributes.ringscan.format: expected {STORE_FORMAT!r}")
    names = attrs.get("frames")
    if (not isinstance(names, list) or len(names) != n or not all(isinstance(x, str) and x for x in names)
            or len(set(names)) != n):
        raise FormatError(meta, f"attributes.ringscan.frames: expected {n} distinct frame names (one per frame)")
    return StoreInfo(path=path, names=tuple(names), height=h, width=w, dtype=np.dtype(_DTYPES[dt]))


def missing_frames(info: StoreInfo) -> list[str]:
    """The frames of a store whose chunk file is not there (a capture in progress)."""
    return [n for i, n in enumerate(info.names) if not info.chunk_path(i).is_file()]


def _blosc():
    from numcodecs import Blosc

    return Blosc


def _encode(img: np.ndarray) -> bytes:
    import crc32c

    Blosc = _blosc()
    shuffle = {"noshuffle": Blosc.NOSHUFFLE, "shuffle": Blosc.SHUFFLE, "bitshuffle": Blosc.BITSHUFFLE}[BLOSC["shuffle"]]
    c = Blosc(cname=BLOSC["cname"], clevel=BLOSC["clevel"], shuffle=shuffle, blocksize=BLOSC["blocksize"])
    data = c.encode(np.ascontiguousarray(img, dtype=img.dtype.newbyteorder("<")))
    return bytes(data) + crc32c.crc32c(data).to_bytes(4, "little")


_scratch = threading.local()


def _chunk_limit(info: StoreInfo) -> int:
    """The largest chunk file a frame of ``info`` may have: the frame's bytes, Blosc's
    header and overhead, the checksum, with room to spare."""
    return info.height * info.width * info.dtype.itemsize + (1 << 20)


def _check_chunk_size(path: Path, size: int, limit: int) -> None:
    if size < 20 or size > limit:
        raise FormatError(path, f"frame chunk of {size} bytes (damaged store)")


def check_chunk_files(info: StoreInfo, names: Sequence[str]) -> None:
    """Check, without decoding them, that the chunk files of ``names`` are there, regular
    files, of a size a frame's chunk can have, and that each one's header holds one frame
    of the store's size and data type (a reader checks them before it writes anything;
    their checksums are checked as they are decoded).

    Raises:
        FormatError: naming the first chunk file missing, not a regular file, of an
            impossible size, or holding another number of bytes than one frame.
    """
    limit = _chunk_limit(info)
    for n in names:
        p = info.chunk_path(info.index(n))
        try:
            st = os.stat(p)
        except FileNotFoundError:
            raise FormatError(p, "frame missing from the frame store") from None
        if not stat.S_ISREG(st.st_mode):
            raise FormatError(p, f"frame chunk is {mode_kind(st.st_mode)}, not a regular file (damaged store)")
        _check_chunk_size(p, st.st_size, limit)
        # the Blosc header's byte count (bytes 4..8): one frame of the metadata's size and data type
        try:
            fd = os.open(p, os.O_RDONLY | getattr(os, "O_NONBLOCK", 0) | getattr(os, "O_CLOEXEC", 0))
            with open(fd, "rb", buffering=0) as f:
                head = f.read(16)
        except OSError as e:
            raise FormatError(p, f"cannot read the frame chunk: {e.strerror}") from None
        held = int.from_bytes(head[4:8], "little")
        if held != info.height * info.width * info.dtype.itemsize:
            raise FormatError(p, f"frame chunk holds {held} bytes, not one {info.width}x{info.height} {info.dtype} "
                                 "frame")


def _read_chunk(path: Path, limit: int) -> memoryview:
    """A chunk file's bytes, in this thread's reusable buffer: no allocation per frame (without
    ringscan's allocator policy, ``kernels.process.retain_freed_memory``, each new ~0.6 MB
    ``bytes`` is mapped and faulted in afresh: 9 ms a view against 1 ms). Valid until this
    thread's next call."""
    try:
        # O_NONBLOCK: a FIFO in a chunk's place cannot block the open (it is refused below)
        fd = os.open(path, os.O_RDONLY | getattr(os, "O_NONBLOCK", 0) | getattr(os, "O_CLOEXEC", 0))
    except FileNotFoundError:
        raise FormatError(path, "frame missing from the frame store") from None
    except OSError as e:
        raise FormatError(path, f"cannot read the frame chunk: {e.strerror}") from None
    with open(fd, "rb", buffering=0) as f:
        st = os.fstat(f.fileno())
        if not stat.S_ISREG(st.st_mode):
            raise FormatError(path, f"frame chunk is {mode_kind(st.st_mode)}, not a regular file (damaged store)")
        size = st.st_size
        _check_chunk_size(path, size, limit)
        buf = getattr(_scratch, "buf", None)
        if buf is None or len(buf) < size:
            buf = _scratch.buf = memoryview(bytearray(size))
        n = 0
        while n < size:
            got = f.readinto(buf[n:size])
            if not got:
                break
            n += got
    if n != size:
        raise FormatError(path, f"frame chunk shorter than its {size} bytes (changed while read)")
    return buf[:size]


def _decode_into(path: Path, out: np.ndarray) -> None:
    """Decode chunk file ``path`` into ``out`` (one frame), checking its CRC32C and size."""
    import crc32c

    raw = _read_chunk(path, out.nbytes + (1 << 20))
    body = raw[:-4]
    if crc32c.crc32c(body) != int.from_bytes(raw[-4:], "little"):
        raise FormatError(path, "frame chunk fails its CRC32C checksum (damaged store)")
    # The Blosc header's byte count (bytes 4..8) must be exactly one frame.
    if int.from_bytes(raw[4:8], "little") != out.nbytes:
        raise FormatError(path, f"frame chunk holds {int.from_bytes(raw[4:8], 'little')} bytes, "
                                f"not one {out.shape[1]}x{out.shape[0]} {out.dtype} frame")
    try:
        _blosc()().decode(body, out=out.view(out.dtype.newbyteorder("<")))
    except Exception as e:  # numcodecs raises RuntimeError/ValueError for a bad stream
        raise FormatError(path, f"frame chunk does not decode ({e})") from None


def read_store(path: str | os.PathLike | StoreInfo, names: Sequence[str] | None = None, *,
               threads: int = 1, out: np.ndarray | None = None) -> np.ndarray:
    """Read frames of a store as one (len(names), H, W) array.

    Args:
        path: the store folder (or its :class:`StoreInfo`).
        names: the frames to read, in this order (default: all, in store order).
        threads: frames decoded at a time (Blosc releases the GIL).
        out: a C-contiguous (len(names), H, W) array of the store's dtype to decode
            into (returned); default a new one.

    Raises:
        FormatError: naming the file: bad metadata, an unknown frame name, a missing
            chunk, a chunk that fails its checksum or does not decode.
    """
    info = path if isinstance(path, StoreInfo) else open_store(path)
    names = list(info.names) if names is None else list(names)
    for n in names:
        if n not in info.names:
            raise FormatError(info.path / "zarr.json", f"frame {n!r} is not in the frame store")
    shape = (len(names), info.height, info.width)
    if out is None:
        out = np.empty(shape, info.dtype)
    elif out.shape != shape or out.dtype != info.dtype or not out.flags.c_contiguous or not out.flags.writeable:
        raise ValueError(f"read_store: out must be a writeable C-contiguous {shape} {info.dtype} array, "
                         f"got {out.shape} {out.dtype}")
    jobs = [(info.chunk_path(info.index(n)), out[i]) for i, n in enumerate(names)]
    # Decoded on pool threads even for threads=1: numcodecs' Blosc then decodes each
    # frame on its calling thread alone (on the main thread it would start Blosc's own
    # threads), so ``threads`` is the number of cores used.
    from concurrent.futures import ThreadPoolExecutor

    with ThreadPoolExecutor(max_workers=max(1, min(int(threads), len(jobs)))) as ex:
        list(ex.map(lambda j: _decode_into(*j), jobs))
    return out


def create_store(path: str | os.PathLike, names: Sequence[str], *, height: int, width: int,
                 dtype=np.uint8) -> StoreInfo:
    """Create an empty store for ``names`` (frames filled in later by :func:`write_frame`).

    An existing store with the same names, size and dtype is kept as it is (a
    capture that resumes); a different one is an error.
    """
    path = Path(path)
    dt = _check_new(names, height, width, dtype)
    if is_store(path):
        info = open_store(path)
        if (info.names, info.height, info.width, info.dtype) != (tuple(names), height, width, dt):
            raise FormatError(path / "zarr.json", "a different frame store is already there")
        return info
    path.mkdir(parents=True, exist_ok=True)
    atomic_write_json(path / "zarr.json", _metadata(names, height, width, dt))
    return StoreInfo(path=path, names=tuple(names), height=int(height), width=int(width), dtype=dt)


def write_frame(info: StoreInfo, name: str, img: np.ndarray) -> None:
    """Write one frame of a store (atomically: a killed writer leaves the old chunk or none)."""
    if img.shape != (info.height, info.width) or img.dtype != info.dtype:
        raise ValueError(f"frame {name!r}: {img.shape} {img.dtype} does not fit the store "
                         f"({info.height}, {info.width}) {info.dtype}")
    p = info.chunk_path(info.index(name))
    p.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_bytes(p, _encode(img))


def _temporary_folder(path: Path) -> Path:
    """A new empty folder beside ``path``, named as atomic writes name their files
    (``.<name>.<pid>-<hex>.tmp``) so that :func:`remove_stale_stores` finds it."""
    for _ in range(100):
        tmp = path.parent / f".{path.name}.{os.getpid()}-{secrets.token_hex(4)}.tmp"
        try:
            tmp.mkdir()
        except FileExistsError:
            continue
        return tmp
    raise FileExistsError(f"{path.parent}: could not create a temporary folder for {path.name}")


def remove_stale_stores(folder: str | os.PathLike) -> list[Path]:
    """Remove the temporary store folders that killed writers left in ``folder``."""
    removed = []
    try:
        entries = list(os.scandir(folder))
    except (FileNotFoundError, NotADirectoryError):
        return removed
    for e in entries:
        m = _TMP_DIR_RE.match(e.name)
        if m and e.is_dir(follow_symlinks=False) and not _process_alive(int(m["pid"])):
            shutil.rmtree(e.path, ignore_errors=True)
            removed.append(Path(e.path))
    return removed


def remove_stale_chunk_temporaries(info: StoreInfo) -> int:
    """Remove the temporary chunk files that killed writers left in a store (a capture
    that resumes). Returns how many."""
    from ringscan.pipeline.formats.atomic import remove_stale_temporaries

    return sum(len(remove_stale_temporaries(info.path / "c" / str(i) / "0")) for i in range(len(info.names))
               if (info.path / "c" / str(i) / "0").is_dir())


def write_store(path: str | os.PathLike, frames: np.ndarray, names: Sequence[str]) -> StoreInfo:
    """Write a whole store at once: into a temporary folder beside ``path``, read
    back and compared frame by frame, then renamed into place (replacing a store
    that is there). Returns the new store's info.

    Args:
        frames: (n, H, W) uint8 or uint16, in the order of ``names``.
    """
    path = Path(path)
    if frames.ndim != 3 or frames.shape[0] != len(names):
        raise ValueError(f"frame store: {frames.shape} frames for {len(names)} names")
    _check_new(names, frames.shape[1], frames.shape[2], frames.dtype)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = _temporary_folder(path)
    try:
        info = create_store(tmp, names, height=frames.shape[1], width=frames.shape[2], dtype=frames.dtype)
        for n, img in zip(names, frames):
            write_frame(info, n, img)
        back = read_store(info)
        if not np.array_equal(back, frames):
            raise FormatError(path, "frame store does not read back as written")
        if path.exists():
            old = _temporary_folder(path)
            os.rmdir(old)
            os.replace(path, old)
            os.replace(tmp, path)
            shutil.rmtree(old, ignore_errors=True)
        else:
            os.replace(tmp, path)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return StoreInfo(path=path, names=tuple(names), height=frames.shape[1], width=frames.shape[2],
                     dtype=frames.dtype)
