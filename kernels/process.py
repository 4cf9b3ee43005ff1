"""The host side of a process ringscan owns (no Warp here: a command that reads frames first, ``ringscan
import``, imports Warp only when its kernels are needed): the allocator's policy, BLAS on one thread and the
exit without a last collection."""

from __future__ import annotations

import ctypes
import logging
import os
import sys

log = logging.getLogger(__name__)
_retained_mb = 0
_skipping = False
_frozen = False


M_TRIM_THRESHOLD = -1
M_MMAP_THRESHOLD = -3
MMAP_THRESHOLD_MAX = 32 << 20
"""glibc's largest ``M_MMAP_THRESHOLD`` on 64-bit systems."""
BLAS_THREADS_ENV = ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS")
"""Environment variables that set a BLAS library's threads: where the user set one, :func:`one_blas_thread`
leaves the choice to them."""
KEEP_FREED_ENV = "RINGSCAN_KEEP_FREED_MB"
"""Environment variable: the most freed memory ringscan's processes keep, in MiB (0: off)."""
DEFAULT_KEEP_FREED_MB = 512


def retain_freed_memory(limit_mb: int | None = None) -> bool:
    """Keep freed host memory in this process, up to ``limit_mb``, for the next view.

    Every view allocates its per-pixel arrays afresh (Warp CPU arrays, decoded
    frames: ~60 MB a 1280x1024 view). With glibc's default policy the larger ones
    are mapped and unmapped each time, or the heap is trimmed back to the system,
    and the next view faults every page in again: a quarter of the CPU kernels'
    time (docs/batch.md). This sets glibc's mmap threshold to its largest value
    (32 MiB: arrays below it come from the heap) and the trim threshold to
    ``limit_mb``. The process's peak memory grows little (413 against 384 MB for
    full-size views); memory it freed is kept for reuse instead of returned.

    It also keeps NumPy's arrays on the base page size: NumPy asks Linux for
    transparent huge pages on every array of 4 MB or more (``madvise``), and under
    the kernel's usual policy for such memory (``defrag = madvise``) a fault may
    compact memory and always clears a whole 2 MB page: on this project's 2-core
    machine a two-camera import of 1920x1280 frames took 1.86-2.01 s with them and
    1.82-1.90 without, its reconstruction 2.00-2.24 against 1.90-1.93 s
    (docs/batch.md, "Real captures").

    Called by the processes ringscan owns (the ``ringscan`` command, batch
    workers, Ray tasks), never on import: a script that uses ringscan as a library
    keeps its own policy unless it calls this.

    Args:
        limit_mb: the most freed memory kept, in MiB; None: the environment's
            ``RINGSCAN_KEEP_FREED_MB`` (``0`` turns the policy off), else 512.

    Returns:
        True where the policy was set; False where it is off or the C library has
        no ``mallopt`` (not glibc: musl, macOS, Windows): nothing changed.
    """
    if limit_mb is None:
        env = os.environ.get(KEEP_FREED_ENV, "").strip()
        try:
            limit_mb = int(env) if env else DEFAULT_KEEP_FREED_MB
        except ValueError:
            log.warning("%s=%r is not a whole number of MiB: using %d", KEEP_FREED_ENV, env, DEFAULT_KEEP_FREED_MB)
            limit_mb = DEFAULT_KEEP_FREED_MB
    if limit_mb <= 0 or not sys.platform.startswith("linux"):
        return False
    try:
        mallopt = ctypes.CDLL(None).mallopt
    except (OSError, AttributeError):
        return False
    mallopt.argtypes = (ctypes.c_int, ctypes.c_int)
    mallopt.restype = ctypes.c_int
    ok = mallopt(M_MMAP_THRESHOLD, MMAP_THRESHOLD_MAX) == 1
    ok = mallopt(M_TRIM_THRESHOLD, int(limit_mb) << 20) == 1 and ok
    if ok:
        global _retained_mb
        _retained_mb = int(limit_mb)
        log.debug("host allocator: mmap threshold %d MiB, trim threshold %d MiB", MMAP_THRESHOLD_MAX >> 20, limit_mb)
        _numpy_base_pages()
    return ok


def _numpy_base_pages() -> None:
    """NumPy's large arrays without its transparent-huge-page advice (see :func:`retain_freed_memory`)."""
    try:
        from numpy._core.multiarray import _set_madvise_hugepage
    except ImportError:  # (NumPy 1.x named its core module without the underscore)
        try:
            from numpy.core.multiarray import _set_madvise_hugepage
        except ImportError:
            return
    _set_madvise_hugepage(False)


def one_blas_thread() -> bool:
    """BLAS on one thread in this process and in the processes it starts (batch workers).

    ringscan's BLAS calls are small (the error model's fit: products of ~40k x 8 matrices, 6 x 6
    solves) and run between Warp's CPU kernels, which take every core. OpenBLAS (NumPy's and SciPy's)
    starts a thread a core and lets its threads spin after each call, waiting for the next: they then
    take the cores from the kernels and from the other batch workers. On this project's 2-core
    machine two batch workers of small views ran at 12-17 views/s, no faster than one, and at 30-31
    with one BLAS thread (1.86x one worker; docs/batch.md). Sets ``OPENBLAS_NUM_THREADS=1`` for the
    libraries loaded from now on and for child processes, and limits those already loaded
    (threadpoolctl). Where the user set ``OPENBLAS_NUM_THREADS``, ``OMP_NUM_THREADS`` or
    ``MKL_NUM_THREADS``, nothing is changed. Called by the processes ringscan owns, like
    :func:`retain_freed_memory`; never on import.

    Returns:
        True where BLAS was set to one thread; False where the user's environment decides.
    """
    if any(os.environ.get(k, "").strip() for k in BLAS_THREADS_ENV):
        return False
    os.environ["OPENBLAS_NUM_THREADS"] = "1"
    from threadpoolctl import threadpool_limits

    threadpool_limits(limits=1, user_api="blas")  # (kept for the process's life: not used as a context)
    return True


def skip_final_collection() -> None:
    """Let this process end without the garbage collector's last passes over every object.

    At exit the interpreter collects everything the imports made (NumPy, SciPy, OpenCV,
    Warp's builtins ...): 0.4-0.5 s on this project's 2-core machine, as much as a small
    view, paid by every ``ringscan`` command and by every batch worker when its pool
    closes (docs/batch.md). :func:`gc.freeze` in an ``atexit`` handler skips those passes;
    the ``atexit`` handlers registered before it (``weakref.finalize``, temporary
    folders, logging's flush) still run after it, every file ringscan writes is already
    closed and flushed, and the operating system frees the memory. Called by the
    processes ringscan owns, like :func:`retain_freed_memory`; registered once.
    """
    global _skipping
    if not _skipping:
        import atexit
        import gc

        atexit.register(gc.freeze)
        _skipping = True


def freeze_imported_objects() -> None:
    """Leave the objects made so far (the imports': NumPy, OpenCV, Warp's builtins ...) out of the
    garbage collector's later passes.

    They live as long as the process; its oldest generation's collections during a run traversed
    them all again (0.09 s of a statue-size camera-camera reconstruction's collections, 0.05 s
    with them frozen: docs/batch.md, "Real captures"). Called by the processes ringscan owns once
    their command's modules are imported, like :func:`skip_final_collection`; once a process (a
    test session calling the command again and again freezes nothing of its own later garbage).
    """
    global _frozen
    if not _frozen:
        import gc

        gc.freeze()
        _frozen = True


def freed_memory_kept_mb() -> int:
    """The most freed memory this process keeps, in MiB, as :func:`retain_freed_memory`
    set it; 0 where the policy is not set (then nothing is kept between views and scans)."""
    return _retained_mb
