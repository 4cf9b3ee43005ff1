"""ringscan.kernels: Warp kernels and thin launch wrappers.

Device-agnostic: stage functions take the device from their input arrays, so the
same code runs on "cpu" and "cuda:N". Nothing here imports ringscan.pipeline or
ringscan.hardware.
"""

from __future__ import annotations

import importlib

__all__ = ["init_warp", "resolve_device", "retain_freed_memory"]

_HOME = {"init_warp": "runtime", "resolve_device": "runtime", "retain_freed_memory": "process"}
"""Where each name lives: imported on first use, so that importing a module of this package that needs no
Warp (``process``) loads none (Warp's import is ~0.2 s of one core)."""


def __getattr__(name: str):
    if name not in _HOME:
        raise AttributeError(f"module 'ringscan.kernels' has no attribute {name!r}")
    value = getattr(importlib.import_module(f"ringscan.kernels.{_HOME[name]}"), name)
    globals()[name] = value
    return value
