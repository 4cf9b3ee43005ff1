"""ringscan.kernels: Warp kernels and thin launch wrappers.

Device-agnostic: stage functions take the device from their input arrays, so the
same code runs on "cpu" and "cuda:N". Nothing here imports ringscan.pipeline or
ringscan.hardware.
"""

from ringscan.kernels.runtime import init_warp, resolve_device, retain_freed_memory

__all__ = ["init_warp", "resolve_device", "retain_freed_memory"]
