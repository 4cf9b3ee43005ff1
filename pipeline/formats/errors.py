"""Errors that ringscan raises for bad input.

Every error names the file (when there is one) and what is wrong, so a user sees
``scan.json: views[2].frames.gray_3: file not found`` instead of a traceback from
deep inside NumPy or Warp.
"""

from __future__ import annotations

import os


class RingscanError(Exception):
    """Base class of every error ringscan raises on purpose."""


class FormatError(RingscanError, ValueError):
    """A file (scan.json, rig file, image, PLY) is missing, unreadable or invalid.

    Args:
        path: the file that is wrong (``None`` for data built in memory).
        message: what is wrong, naming the field where there is one.
    """

    def __init__(self, path: str | os.PathLike | None, message: str):
        self.path = None if path is None else os.fspath(path)
        self.message = message
        super().__init__(f"{show_path(self.path)}: {message}" if self.path else message)


def show_path(path: str | os.PathLike) -> str:
    """A path as a message shows it: as it is, or quoted with escapes when it holds
    characters a terminal cannot show (a NUL, a newline, other control characters)."""
    p = os.fspath(path)
    if isinstance(p, bytes):
        p = os.fsdecode(p)
    return p if p.isprintable() else repr(p)
