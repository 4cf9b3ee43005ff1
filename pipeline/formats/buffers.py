"""Reusable frame stacks: a view's (n, H, W) frames read into memory a process already has.

A full-size view's frames are ~37 MB (28 frames of 1280x1024): above glibc's largest
mmap threshold (32 MiB), so a fresh ``np.empty`` per view is mapped anew and every page
of it faulted in and zeroed by the kernel while the frames are decoded into it, ~5 % of
a packed view's CPU (docs/batch.md). A reconstruction that reads view after view
takes its stacks from a :class:`FrameBuffers` and gives them back when the view is
done, so the same memory is written again instead.
"""

from __future__ import annotations

import threading

import numpy as np

__all__ = ["FrameBuffers"]


class FrameBuffers:
    """A small pool of frame stacks, safe to share between threads.

    :meth:`take` returns a free stack of the asked shape and dtype (or a new one);
    :meth:`give` returns one to the pool, which keeps at most ``keep`` stacks and
    at most ``max_bytes`` of them (the oldest dropped first; None: no byte bound).
    A stack given back must no longer be used by its taker.
    """

    def __init__(self, keep: int = 2, max_bytes: int | None = None):
        if keep < 0:
            raise ValueError(f"keep must be >= 0, got {keep}")
        if max_bytes is not None and max_bytes < 0:
            raise ValueError(f"max_bytes must be >= 0, got {max_bytes}")
        self.keep = int(keep)
        self.max_bytes = None if max_bytes is None else int(max_bytes)
        self._free: list[np.ndarray] = []
        self._lock = threading.Lock()

    def take(self, shape: tuple[int, ...], dtype) -> np.ndarray:
        """An uninitialised C-contiguous array of ``shape`` and ``dtype``."""
        shape, dtype = tuple(int(s) for s in shape), np.dtype(dtype)
        with self._lock:
            for i, a in enumerate(self._free):
                if a.shape == shape and a.dtype == dtype:
                    return self._free.pop(i)
        return np.empty(shape, dtype)

    def give(self, arr: np.ndarray) -> None:
        """Return ``arr`` (taken from this pool or not) for a later :meth:`take`."""
        if self.keep == 0 or not isinstance(arr, np.ndarray) or not arr.flags.c_contiguous or not arr.flags.owndata:
            return
        with self._lock:
            if any(a is arr for a in self._free):
                return
            self._free.append(arr)
            del self._free[:-self.keep]
            if self.max_bytes is not None:
                while self._free and sum(a.nbytes for a in self._free) > self.max_bytes:
                    self._free.pop(0)

    def clear(self) -> None:
        """Drop every kept stack."""
        with self._lock:
            self._free.clear()
