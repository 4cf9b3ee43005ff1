"""ringscan: structured-light 3D scanning with concentric ring patterns (Lee & Krim).

The Python API (docs/api.md), plain functions from a scan to clouds, a fused object, a
mesh and figures::

    import ringscan

    scan = ringscan.load_scan("out/demo/scan")   # or ringscan.simulate(folder, ...)
    views = ringscan.reconstruct(scan)           # per view: an Open3D tensor cloud and its pose
    fused = ringscan.fuse(views)                 # o3d.t.geometry.PointCloud, object frame
    mesh = ringscan.mesh(fused)                  # o3d.t.geometry.TriangleMesh
    print(ringscan.evaluate(views, scan)["all"])

The sub-packages are the layers (docs/architecture.md): ``ringscan.kernels``,
``ringscan.pipeline`` (every stage's own API), ``ringscan.hardware`` and
``ringscan.tools`` (the ``ringscan`` command); ``ringscan.api`` holds the functions
above. Importing ``ringscan`` alone loads none of them (no Warp, no Open3D): a name
of the API is imported on its first use.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    # The API as plain imports, for import-linter (which reads imports under TYPE_CHECKING
    # too: a module taking a name from here depends on ringscan.api) and for type checkers.
    # At run time __getattr__ loads them on first use.
    from ringscan.api import ReconstructedView, evaluate, fuse, load_scan, mesh, reconstruct, simulate

_API = ("ReconstructedView", "evaluate", "fuse", "load_scan", "mesh", "reconstruct", "simulate")
"""The names taken from ringscan.api; the same as the TYPE_CHECKING import above (a test checks it)."""

__all__ = ["__version__", *_API]


def __getattr__(name: str):
    if name == "__version__":  # (read from the installed metadata when asked: importlib.metadata costs ~25 ms)
        value = _installed_version()
    elif name in _API:
        value = getattr(importlib.import_module("ringscan.api"), name)
    else:
        raise AttributeError(f"module 'ringscan' has no attribute {name!r}")
    globals()[name] = value
    return value


def _installed_version() -> str:
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("ringscan")
    except PackageNotFoundError:  # imported from a source tree that was never installed
        return "0+unknown"


def __dir__():
    return sorted(set(globals()) | {"__version__", *_API})
