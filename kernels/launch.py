"""Launch helpers shared by every kernel module: the CPU launch pool.

On CUDA a stage is one launch. On Warp's CPU backend a launch runs on one
thread, so :func:`launch_rows` (row-run kernels over an image) and
:func:`launch_spans` (1-D kernels over samples or points) cut the work into
slices and launch them from a small process-wide thread pool: launches release
the GIL, so the slices use every core. The first launch of a kernel signature runs
alone on the calling thread (Warp's module loading is not thread-safe).

Device side, :func:`row_run` maps a row-run thread to its pixels. Variable-length
outputs are counted per item, scanned (:func:`scan_counts`, ``wp.utils.array_scan``)
and then written at their offsets: deterministic order, no size guesses.
"""

from __future__ import annotations

import os
import threading
from concurrent.futures import ThreadPoolExecutor

import numpy as np
import warp as wp

wp.set_module_options({"enable_backward": False})  # no gradients are taken here: no adjoint code to compile

__all__ = ["row_run", "launch_rows", "launch_spans", "default_threads", "cpu_threads", "set_cpu_threads",
           "scan_counts", "check_array", "cpu_pool"]


@wp.func
def row_run(tid: int, w: int, row0: int, chunk: int):
    """(y, x0, x1) of row-run thread ``tid``: ``chunk`` pixels of one row of a W-wide
    image, from row ``row0`` on (see :func:`launch_rows`)."""
    n_chunks = (w + chunk - 1) / chunk
    y = row0 + tid / n_chunks
    x0 = (tid - (tid / n_chunks) * n_chunks) * chunk
    return wp.vec3i(y, x0, wp.min(x0 + chunk, w))


# ----------------------------------------------------------------------------- host


def scan_counts(counts: wp.array) -> tuple[wp.array, int]:
    """Exclusive prefix sum of per-item ``counts`` (int32, read) and their total.

    Returns (offsets, total): ``offsets`` (same shape, int32) is where each item's
    outputs start, on the counts' device.
    """
    offsets = wp.empty_like(counts)
    if counts.size == 0:
        return offsets, 0
    with wp.ScopedDevice(counts.device):  # Warp's CUDA scan runs on the current device's context, not the array's
        wp.utils.array_scan(counts, offsets, inclusive=False)
    last = counts.flatten() if counts.ndim > 1 else counts
    offs = offsets.flatten() if offsets.ndim > 1 else offsets
    return offsets, int(offs[-1:].numpy()[0] + last[-1:].numpy()[0])


def _row_slices(h: int, n: int) -> list[tuple[int, int]]:
    n = max(1, min(n, h))
    edges = np.linspace(0, h, n + 1).astype(int)
    return [(int(a), int(b)) for a, b in zip(edges[:-1], edges[1:]) if b > a]


def _one_launch(dev) -> bool:
    """Whether a stage on ``dev`` is one launch of a thread per pixel or item (CUDA),
    not slices of rows or spans launched from the CPU pool. One name for the
    choice, so that the tests can run CUDA's launch geometry on the CPU backend."""
    return dev.is_cuda


_warmed: set = set()
_warm_lock = threading.Lock()
MIN_SLICE_PIXELS = 1 << 16
"""The fewest pixels a CPU slice of a row-run launch covers (:func:`launch_rows`)."""


def _launch_key(kernel, inputs, device) -> tuple:
    return (kernel.key, str(device), tuple(getattr(a, "dtype", type(a)).__name__ if isinstance(a, wp.array)
                                            else type(a).__name__ for a in inputs))


def _launch_slices(kernel, slices, inputs_fn, outputs, dev, threads: int) -> None:
    """Launch ``kernel`` once per ``(a, b)`` slice (dim ``b - a``), from a thread pool.

    The first launch of a kernel signature (which builds or loads its module)
    runs on the calling thread, one caller at a time: Warp's module loading is not thread-safe.
    """
    slices = list(slices)
    if not slices:
        return

    def run(sl):
        a, b = sl
        wp.launch(kernel, dim=b - a, inputs=inputs_fn(a), outputs=outputs, device=dev)

    key = _launch_key(kernel, inputs_fn(slices[0][0]) + list(outputs), dev)
    if key not in _warmed:
        # callers on threads of their own (an import's cameras) meet here too: one loads, the others wait
        with _warm_lock:
            if key not in _warmed:
                run(slices.pop(0))
                _warmed.add(key)
    if threads <= 1:
        for sl in slices:
            run(sl)
        return
    if len(slices) <= 1:  # one slice: the pool's hand-off would cost more than it gives
        for sl in slices:
            run(sl)
        return
    list(_pool(threads).map(run, slices))


_pools: dict = {}


_pool_lock = threading.Lock()


def cpu_pool(threads: int):
    """The process-wide pool of ``threads`` threads (for host code that launches CPU kernels on threads of its
    own, as :func:`launch_rows` does)."""
    return _pool(threads)


def _pool(threads: int):
    """A process-wide thread pool per thread count (starting threads on every
    launch costs more than a small kernel)."""
    with _pool_lock:
        ex = _pools.get(threads)
        if ex is None:
            ex = _pools[threads] = ThreadPoolExecutor(max_workers=threads, thread_name_prefix="ringscan-launch")
        return ex


def launch_rows(kernel, h: int, w: int, inputs_fn, outputs, device, threads: int) -> None:
    """Launch a row-run kernel over an H x W image.

    The kernel's inputs end with ``row0, chunk``: each thread covers ``chunk``
    pixels of one row. On CUDA ``chunk`` is 1 (a thread per pixel, one launch);
    on the CPU ``chunk`` is the whole row and the rows are split into slices
    launched from a small thread pool: each Warp CPU launch runs on one thread
    and releases the GIL, so the slices use every core. ``inputs_fn(row0, chunk)``
    returns the kernel's inputs.
    """
    dev = wp.get_device(device)
    if _one_launch(dev):
        wp.launch(kernel, dim=h * w, inputs=inputs_fn(0, 1), outputs=outputs, device=dev)
        return
    # at least MIN_SLICE_PIXELS a slice: a small image's rows cut in eight cost more in the pool's hand-offs than
    # the cores give (a 320 x 240 view on two threads: 55-56 -> 52-54 ms with this and one slice run in place)
    slices = _row_slices(h, min(threads * 4 if threads > 1 else 1, max(1, h * w // MIN_SLICE_PIXELS)))
    _launch_slices(kernel, slices, lambda a: inputs_fn(a, w), outputs, dev, threads)


def launch_spans(kernel, n: int, inputs_fn, outputs, device, threads: int, *, min_span: int = 4096) -> None:
    """Launch a 1-D kernel over ``n`` items, split into spans on the CPU.

    The kernel's last input is the span's first index ``i0`` (thread ``t``
    handles item ``i0 + t``); ``inputs_fn(i0)`` returns the kernel's inputs.
    On CUDA it is one launch of ``n`` threads; on the CPU the items are cut
    into spans of at least ``min_span`` launched from a thread pool.
    """
    dev = wp.get_device(device)
    if n <= 0:
        return
    if _one_launch(dev):
        wp.launch(kernel, dim=n, inputs=inputs_fn(0), outputs=outputs, device=dev)
        return
    pieces = max(1, min(threads * 4 if threads > 1 else 1, n // max(1, min_span)))
    edges = np.linspace(0, n, pieces + 1).astype(int)
    slices = [(int(a), int(b)) for a, b in zip(edges[:-1], edges[1:]) if b > a]
    _launch_slices(kernel, slices, inputs_fn, outputs, dev, threads)


_cpu_threads: int | None = None


def set_cpu_threads(n: int | None) -> None:
    """Set this process's CPU thread budget for Warp CPU launches and frame reading
    (None: every core). A batch worker sharing the machine with others sets its share."""
    global _cpu_threads
    if n is not None and (isinstance(n, bool) or not isinstance(n, int) or n < 1):
        raise ValueError(f"set_cpu_threads: expected a whole number >= 1 or None, got {n!r}")
    _cpu_threads = n


def cpu_threads() -> int:
    """This process's CPU thread budget: what :func:`set_cpu_threads` set, else the core count."""
    return _cpu_threads or os.cpu_count() or 1


def default_threads() -> int:
    """Threads for one stage's CPU launches: the budget, at most 8."""
    return max(1, min(8, cpu_threads()))


def check_array(name: str, a, n: int | None, dtype, fn: str) -> int:
    """A host function's argument check: ``a`` a 1-D Warp array of ``dtype`` (of length ``n``
    unless None); its length. ``fn`` names the function in the message."""
    if not isinstance(a, wp.array) or a.dtype != dtype or a.ndim != 1 or (n is not None and a.shape[0] != n):
        shape = f"({n},)" if n is not None else "1-D"
        raise ValueError(f"{fn}: {name} must be a {shape} {dtype.__name__} Warp array")
    return a.shape[0]
