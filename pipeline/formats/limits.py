"""Bounded reads: only regular files, of a bounded size; images checked by their header before decoding.

Every file ringscan reads goes through one of these guards, so a FIFO (which would
block forever), ``/dev/zero`` (which never ends), a 20 GB JSON file or a 937 KB PNG
that decodes to 30000x30000 pixels (20 GB in memory) is refused with one line naming
the file, before anything is read or decoded. The bounds are constants below
(documented in docs/bad_input.md): ours, generous for any real rig or camera,
small enough that reading the largest accepted file cannot exhaust a workstation.
"""

from __future__ import annotations

import os
import stat
import struct
from pathlib import Path

from ringscan.pipeline.formats.errors import FormatError

__all__ = ["MAX_JSON_BYTES", "MAX_IMAGE_SIDE", "MAX_IMAGE_PIXELS", "mode_kind", "check_regular_file",
           "read_bounded_bytes", "read_bounded_text", "image_header_size", "image_header_colour", "check_image_header"]

MAX_JSON_BYTES = 64 * 1024 * 1024
"""Largest JSON file read (scan.json, rig files, settings, reports): 64 MiB (a scan.json
of 10 000 views is ~3 MB)."""

MAX_IMAGE_SIDE = 65536
"""Widest or tallest image read, px (the rig file's largest camera or projector size)."""

MAX_IMAGE_PIXELS = 200_000_000
"""Most pixels of an image read: 200 megapixels (a 16-bit frame of that size is 400 MB;
the largest industrial camera sensors are ~150 MP)."""


def mode_kind(mode: int) -> str:
    """What a file of this ``st_mode`` is, in words, when it is not a regular file."""
    if stat.S_ISDIR(mode):
        return "a folder"
    if stat.S_ISFIFO(mode):
        return "a pipe (FIFO)"
    if stat.S_ISCHR(mode) or stat.S_ISBLK(mode):
        return "a device"
    if stat.S_ISSOCK(mode):
        return "a socket"
    return "not a regular file"


def check_regular_file(path: str | os.PathLike, *, what: str = "file", max_bytes: int | None = None) -> int:
    """Check that ``path`` is a regular file (links followed) of at most ``max_bytes``; return its size.

    Raises:
        FormatError: naming the path: not found, a folder, a pipe, a device, or too large.
    """
    p = Path(path)
    if "\0" in os.fspath(p):
        raise FormatError(p, "the path contains a NUL character")
    try:
        st = p.stat()
    except FileNotFoundError:
        raise FormatError(p, f"{what} not found") from None
    except OSError as e:
        raise FormatError(p, f"cannot read: {e.strerror}") from None
    if not stat.S_ISREG(st.st_mode):
        raise FormatError(p, f"is {mode_kind(st.st_mode)}, not a regular file: ringscan reads regular files only")
    if max_bytes is not None and st.st_size > max_bytes:
        raise FormatError(p, f"{st.st_size} bytes: larger than the {max_bytes} bytes a {what} may have")
    return st.st_size


def read_bounded_bytes(path: str | os.PathLike, max_bytes: int, *, what: str = "file") -> bytes:
    """The bytes of a regular file of at most ``max_bytes`` (refused before reading otherwise).

    The read itself stops at ``max_bytes + 1`` bytes, so a file that grows while it is
    read is refused too.

    Raises:
        FormatError: see :func:`check_regular_file`; also an OS error while reading.
    """
    p = Path(path)
    check_regular_file(p, what=what, max_bytes=max_bytes)
    try:
        # O_NONBLOCK: a path swapped for a FIFO between the check and the open cannot block the open
        fd = os.open(p, os.O_RDONLY | getattr(os, "O_NONBLOCK", 0) | getattr(os, "O_CLOEXEC", 0))
    except OSError as e:
        raise FormatError(p, f"cannot read: {e.strerror}") from None
    with os.fdopen(fd, "rb") as f:
        if not stat.S_ISREG(os.fstat(f.fileno()).st_mode):
            raise FormatError(p, "is not a regular file: ringscan reads regular files only")
        try:
            data = f.read(max_bytes + 1)
        except OSError as e:
            raise FormatError(p, f"cannot read: {e.strerror}") from None
    if len(data) > max_bytes:
        raise FormatError(p, f"larger than the {max_bytes} bytes a {what} may have")
    return data


def read_bounded_text(path: str | os.PathLike, max_bytes: int, *, what: str = "text file") -> str:
    """The UTF-8 text (a BOM allowed) of a regular file of at most ``max_bytes``.

    Raises:
        FormatError: see :func:`read_bounded_bytes`; also a byte that is not UTF-8.
    """
    raw = read_bounded_bytes(path, max_bytes, what=what)
    try:
        return raw.decode("utf-8-sig")
    except UnicodeDecodeError as e:
        raise FormatError(path, f"not a text file: byte 0x{raw[e.start]:02x} at offset {e.start} is not "
                                "UTF-8") from None


# ----------------------------------------------------------------------------- image headers

_PNG = b"\x89PNG\r\n\x1a\n"


def _tiff_size(f, head: bytes) -> tuple[int, int] | None:
    """Width and height of a TIFF's first image (classic or BigTIFF), None when unreadable."""
    bo = "<" if head[:2] == b"II" else ">"
    version = struct.unpack(bo + "H", head[2:4])[0]
    if version == 42:
        off = struct.unpack(bo + "I", head[4:8])[0]
        count_fmt, entry_size, count_size = "H", 12, 2
    elif version == 43:
        off = struct.unpack(bo + "Q", head[8:16])[0]
        count_fmt, entry_size, count_size = "Q", 20, 8
    else:
        return None
    f.seek(off)
    raw = f.read(count_size)
    if len(raw) != count_size:
        return None
    n = min(struct.unpack(bo + count_fmt, raw)[0], 4096)
    entries = f.read(n * entry_size)
    size = {}
    for i in range(len(entries) // entry_size):
        e = entries[i * entry_size:(i + 1) * entry_size]
        tag, typ = struct.unpack(bo + "HH", e[:4])
        if tag not in (256, 257):
            continue
        val = e[8:] if version == 42 else e[12:]
        if typ == 3:  # SHORT
            size[tag] = struct.unpack(bo + "H", val[:2])[0]
        elif typ == 4:  # LONG
            size[tag] = struct.unpack(bo + "I", val[:4])[0]
        elif typ == 16:  # LONG8 (BigTIFF)
            size[tag] = struct.unpack(bo + "Q", val[:8])[0]
    if 256 in size and 257 in size:
        return size[256], size[257]
    return None


def _jpeg_frame_header(f) -> bytes | None:
    """The first 6 bytes of a JPEG's start-of-frame segment (precision, height, width,
    components), None when unreadable."""
    f.seek(2)
    for _ in range(10000):
        b = f.read(1)
        while b and b != b"\xff":
            b = f.read(1)
        while b == b"\xff":
            b = f.read(1)
        if not b:
            return None
        marker = b[0]
        if marker in (0xD8, 0x01) or 0xD0 <= marker <= 0xD7:
            continue
        raw = f.read(2)
        if len(raw) != 2:
            return None
        length = struct.unpack(">H", raw)[0]
        if 0xC0 <= marker <= 0xCF and marker not in (0xC4, 0xC8, 0xCC):
            seg = f.read(6)
            return seg if len(seg) == 6 else None
        f.seek(length - 2, 1)
    return None


def _jpeg_size(f) -> tuple[int, int] | None:
    """Width and height from a JPEG's start-of-frame marker, None when unreadable."""
    seg = _jpeg_frame_header(f)
    if seg is None:
        return None
    h, w = struct.unpack(">HH", seg[1:5])
    return w, h


def _tiff_colour(f, head: bytes) -> bool | None:
    """Whether a TIFF's first image is colour (RGB, YCbCr, CMYK or a palette: Photometric 2, 3, 5, 6, or 3 or
    more samples a pixel), None when unreadable."""
    bo = "<" if head[:2] == b"II" else ">"
    version = struct.unpack(bo + "H", head[2:4])[0]
    if version == 42:
        off, count_fmt, entry_size, count_size, val_at = struct.unpack(bo + "I", head[4:8])[0], "H", 12, 2, 8
    elif version == 43:
        off, count_fmt, entry_size, count_size, val_at = struct.unpack(bo + "Q", head[8:16])[0], "Q", 20, 8, 12
    else:
        return None
    f.seek(off)
    raw = f.read(count_size)
    if len(raw) != count_size:
        return None
    n = min(struct.unpack(bo + count_fmt, raw)[0], 4096)
    entries = f.read(n * entry_size)
    photometric, samples = None, 1
    for i in range(len(entries) // entry_size):
        e = entries[i * entry_size:(i + 1) * entry_size]
        tag, typ = struct.unpack(bo + "HH", e[:4])
        if tag in (262, 277) and typ == 3:  # SHORT
            v = struct.unpack(bo + "H", e[val_at:val_at + 2])[0]
            photometric, samples = (v, samples) if tag == 262 else (photometric, v)
    return photometric in (2, 3, 5, 6) or samples >= 3


def _jpeg_colour(f) -> bool | None:
    """Whether a JPEG holds more than one component (colour), from its start-of-frame marker; None when unreadable."""
    seg = _jpeg_frame_header(f)
    return None if seg is None else seg[5] > 1


def _bmp_colour(f, head: bytes) -> bool | None:
    """Whether a BMP is colour: more than 8 bits a pixel, or a palette with a colour that is not grey."""
    if len(head) < 30:
        return None
    bpp = struct.unpack("<H", head[28:30])[0]
    if bpp > 8:
        return True
    f.seek(14)
    info = f.read(40)
    if len(info) < 36:
        return None
    size = struct.unpack("<I", info[:4])[0]
    used = struct.unpack("<I", info[32:36])[0] or (1 << bpp)
    f.seek(14 + size)
    pal = f.read(4 * min(used, 256))
    return any(not (pal[i] == pal[i + 1] == pal[i + 2]) for i in range(0, len(pal) - 3, 4))


def image_header_colour(path: str | os.PathLike) -> bool | None:
    """Whether a PNG, TIFF, JPEG or BMP file holds colour, from its header (a palette PNG counts as colour);
    None for another format or a header that cannot be parsed."""
    with open(path, "rb") as f:
        head = f.read(32)
        if head.startswith(_PNG) and head[12:16] == b"IHDR" and len(head) >= 26:
            return head[25] in (2, 3, 6)  # RGB, palette, RGBA (0: grey, 4: grey and alpha)
        if head[:2] in (b"II", b"MM") and len(head) >= 16:
            return _tiff_colour(f, head)
        if head[:2] == b"\xff\xd8":
            return _jpeg_colour(f)
        if head[:2] == b"BM":
            return _bmp_colour(f, head)
    return None


def image_header_size(path: str | os.PathLike) -> tuple[int, int] | None:
    """(width, height) of a PNG, TIFF, JPEG or BMP file from its header, without decoding it;
    None for another format or a header that cannot be parsed (the decoder then says what is wrong)."""
    with open(path, "rb") as f:
        head = f.read(32)
        if head.startswith(_PNG) and head[12:16] == b"IHDR":
            return struct.unpack(">II", head[16:24])
        if head[:2] in (b"II", b"MM") and len(head) >= 16:
            return _tiff_size(f, head)
        if head[:2] == b"\xff\xd8":
            return _jpeg_size(f)
        if head[:2] == b"BM" and len(head) >= 26:
            w, h = struct.unpack("<ii", head[18:26])
            return abs(w), abs(h)
    return None


def check_image_header(path: str | os.PathLike, *, max_pixels: int = MAX_IMAGE_PIXELS,
                       max_side: int = MAX_IMAGE_SIDE) -> tuple[int, int]:
    """Refuse an image file that is not a regular file, not a PNG, TIFF, JPEG or BMP, or
    whose header gives more pixels than the bounds, before it is decoded. Returns
    (width, height) from the header.

    Raises:
        FormatError: naming the file: not found, not a regular file, another format
            or a header that cannot be read, or e.g.
            ``image is 30000x30000 (900 megapixels): larger than ringscan reads (at most 65536 px a side, 200 megapixels)``.
    """
    check_regular_file(path, what="image file")
    try:
        size = image_header_size(path)
    except (OSError, struct.error):
        size = None
    if size is None:
        raise FormatError(path, "not a readable image (corrupt file or unsupported format; ringscan reads PNG, "
                                "TIFF, JPEG and BMP)")
    w, h = size
    if w > max_side or h > max_side or w * h > max_pixels:
        raise FormatError(path, f"image is {w}x{h} ({w * h / 1e6:.0f} megapixels): larger than ringscan reads "
                                f"(at most {max_side} px a side, {max_pixels / 1e6:.0f} megapixels)")
    return size
