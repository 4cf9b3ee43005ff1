"""Warp start-up: quiet banner, one init, device names checked at the edge (the host allocator's policy
for processes ringscan owns: ``kernels.process``)."""

from __future__ import annotations

import contextlib
import logging
import os
import sys
import tempfile
import threading

import warp as wp

log = logging.getLogger(__name__)
_initialised = False
_init_lock = threading.Lock()


def init_warp() -> None:
    """Initialise Warp once, quietly (the kernel cache makes later runs fast); safe from any thread.

    ``wp.init()`` itself is not: threads that call it at once (an import's cameras) each make a runtime, and
    each marks every kernel module modified, under a module another thread is loading."""
    global _initialised
    if _initialised:
        return
    with _init_lock:
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
