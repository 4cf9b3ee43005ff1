"""Frame images: 8- or 16-bit PNG/TIFF, grey or colour (converted to grey), written atomically."""

from __future__ import annotations

import logging
import os
from pathlib import Path

import numpy as np

from ringscan.pipeline.formats.atomic import atomic_path
from ringscan.pipeline.formats.errors import FormatError

log = logging.getLogger(__name__)

__all__ = ["read_image", "write_image"]


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
