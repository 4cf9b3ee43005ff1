"""Warp start-up: quiet banner, one init, device names checked at the edge."""

from __future__ import annotations

import logging
import os

import warp as wp

log = logging.getLogger(__name__)
_initialised = False


def init_warp() -> None:
    """Initialise Warp once, quietly (the kernel cache makes later runs fast)."""
    global _initialised
    if _initialised:
        return
    verbose = os.environ.get("RINGSCAN_WARP_VERBOSE", "") != ""
    wp.config.quiet = not verbose
    wp.config.log_level = logging.INFO if verbose else logging.ERROR
    wp.init()
    _initialised = True


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
