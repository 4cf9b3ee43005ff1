"""ringscan: structured-light 3D scanning with concentric ring patterns (Lee & Krim).

The sub-packages are the layers (docs/architecture.md): ``ringscan.kernels``,
``ringscan.pipeline`` (the public Python API), ``ringscan.hardware`` and
``ringscan.tools`` (the ``ringscan`` command). Importing ``ringscan`` alone loads
none of them (no Warp, no Open3D).
"""

from importlib.metadata import PackageNotFoundError, version

try:
    __version__ = version("ringscan")
except PackageNotFoundError:  # imported from a source tree that was never installed
    __version__ = "0+unknown"

__all__ = ["__version__"]
