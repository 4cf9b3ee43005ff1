"""Warp start-up: quiet banner, one init, device names checked at the edge; the
host allocator's policy for processes ringscan owns."""

from __future__ import annotations

import contextlib
import ctypes
import logging
import os
import sys
import tempfile

import warp as wp

log = logging.getLogger(__name__)
_initialised = False
_retained_mb = 0
_skipping = False


def init_warp() -> None:
    """Initialise Warp once, quietly (the kernel cache makes later runs fast)."""
    global _initialised
    if _initialised:
        return
    verbose = os.environ.get("RINGSCAN_WARP_VERBOSE", "") != ""
    wp.config.quiet = not verbose
    wp.config.log_level = logging.INFO if verbose else logging.ERROR
    with contextlib.nullcontext() if verbose else _native_stderr_to_log():
        wp.init()
    _initialised = True


@contextlib.contextmanager
def _native_stderr_to_log():
    """Send what Warp's native library prints on stderr during start-up to the log.

    On a machine without CUDA, ``wp.init()`` prints "Warp CUDA warning: Could not
    find or load the NVIDIA CUDA driver" with C ``fprintf`` (out of reach of
    ``wp.config.quiet``): expected there, so it is logged at INFO (``ringscan -v``
    shows it); anything else it prints is logged as a warning.
    """
    try:
        sys.stderr.flush()
        saved = os.dup(2)
    except (OSError, ValueError, AttributeError):  # no file descriptor 2 to borrow
        yield
        return
    with tempfile.TemporaryFile() as tmp:
        os.dup2(tmp.fileno(), 2)
        try:
            yield
        finally:
            with contextlib.suppress(OSError, ValueError, AttributeError):
                sys.stderr.flush()
            os.dup2(saved, 2)
            os.close(saved)
            tmp.seek(0)
            text = tmp.read().decode("utf-8", "replace")
    for line in text.splitlines():
        if line.strip():
            log.log(logging.INFO if "CUDA driver" in line else logging.WARNING, "%s", line.strip())


KERNEL_PACKAGE = "ringscan.kernels"


def uncached_kernel_modules(device: str = "cpu", modules=None) -> list[str] | None:
    """The Warp modules of :mod:`ringscan.kernels` that Warp's kernel cache holds no
    compiled binary of for ``device``: those Warp compiles at their first launch
    (seconds each on a CPU; a fresh machine, a new Warp version or changed kernel
    code). Warp keeps each module's binaries in ``<kernel_cache_dir>/wp_<module>_<hash>/``,
    the hash over the module's code and options (block size 1 on a CPU).

    ``modules``: the module names to check (``"raytrace"`` or ``"ringscan.kernels.raytrace"``;
    None: every one). Imports them (as a scan does anyway); logs nothing.

    Returns:
        The module names (empty: all cached), or None where the cache cannot be read
        this way (another Warp version's layout).
    """
    import importlib
    import pkgutil

    resolved = resolve_device(device)
    try:
        dev = wp.get_device(resolved)
        package = importlib.import_module(KERNEL_PACKAGE)
        names = ([f"{KERNEL_PACKAGE}.{i.name}" for i in pkgutil.iter_modules(package.__path__)] if modules is None
                 else [m if m.startswith(KERNEL_PACKAGE + ".") else f"{KERNEL_PACKAGE}.{m}" for m in modules])
        cold = []
        for name in names:
            importlib.import_module(name)
            module = wp.get_module(name)
            if not module.kernels:
                continue
            block_dim = 1 if dev.is_cpu else module.options["block_dim"]
            folder = os.path.join(wp.config.kernel_cache_dir, module.get_module_identifier(block_dim=block_dim))
            if dev.is_cpu:
                cached = os.path.isfile(os.path.join(folder, module._get_compile_output_name(dev, block_dim=block_dim)))
            else:  # one binary a GPU architecture: any counts
                cached = os.path.isdir(folder) and any(f.endswith((".ptx", ".cubin")) for f in os.listdir(folder))
            if not cached:
                cold.append(name)
        return cold
    except (AttributeError, TypeError, KeyError, OSError) as e:
        log.debug("could not read Warp's kernel cache: %s", e)
        return None


def resolve_device(device: str | None) -> str:
    """Check a device name given by the user ("cpu", "cuda", "cuda:0", or None =
    the best available) and return Warp's name for it.

    Raises:
        ValueError: for an unknown device or CUDA on a machine without it.
    """
    init_warp()
    if device in (None, "", "auto"):
        return "cuda:0" if wp.is_cuda_available() else "cpu"
    if device == "cuda":
        device = "cuda:0"
    if device.startswith("cuda") and not wp.is_cuda_available():
        raise ValueError(f"device {device!r}: CUDA is not available on this machine (use --device cpu)")
    try:
        return str(wp.get_device(device))
    except Exception:
        raise ValueError(f"device {device!r}: unknown (known: {', '.join(str(d) for d in wp.get_devices())})") from None


M_TRIM_THRESHOLD = -1
M_MMAP_THRESHOLD = -3
MMAP_THRESHOLD_MAX = 32 << 20
"""glibc's largest ``M_MMAP_THRESHOLD`` on 64-bit systems."""
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
    return ok


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


def freed_memory_kept_mb() -> int:
    """The most freed memory this process keeps, in MiB, as :func:`retain_freed_memory`
    set it; 0 where the policy is not set (then nothing is kept between views and scans)."""
    return _retained_mb
