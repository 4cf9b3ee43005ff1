"""Image files whose headers claim a size their data does not have (small on disk, huge decoded), for the
tests of bounded reads: an image's header is checked before it is decoded."""

from __future__ import annotations

import struct
import zlib


def png_header_only(path, w, h, bit_depth=8):
    """A PNG whose IHDR claims w x h (grey) and whose data is a few bytes: small on disk, huge decoded."""
    def chunk(kind, data):
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))
    ihdr = struct.pack(">IIBBBBB", w, h, bit_depth, 0, 0, 0, 0)
    path.write_bytes(b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IDAT", zlib.compress(b"\0" * 64))
                     + chunk(b"IEND", b""))
    return path


def tiff_header_only(path, w, h, big_endian=False):
    """A TIFF whose one IFD claims w x h (8-bit grey) and that holds no image data."""
    bo = ">" if big_endian else "<"
    entries = [(256, 4, 1, w), (257, 4, 1, h), (258, 3, 1, 8), (277, 3, 1, 1)]
    ifd = struct.pack(bo + "H", len(entries)) + b"".join(
        struct.pack(bo + "HHI", t, typ, n) + (struct.pack(bo + "HH", v, 0) if typ == 3 else struct.pack(bo + "I", v))
        for t, typ, n, v in entries) + struct.pack(bo + "I", 0)
    path.write_bytes((b"MM" if big_endian else b"II") + struct.pack(bo + "HI", 42, 8) + ifd)
    return path


def huge_png(path, w=60000, h=60000):
    """:func:`png_header_only` of a 60000x60000 frame (3600 megapixels): the batch tests' frame too large to
    decode."""
    return png_header_only(path, w, h)
