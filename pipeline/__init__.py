"""ringscan.pipeline: scan folders in, point clouds, meshes and reports out.

Sub-packages, in the order data flows (each imports only those below it; the
import-linter contract in pyproject.toml checks it):

- :mod:`~ringscan.pipeline.formats`: scan folders, rig files, patterns, settings,
  PLY, meshes, images, atomic writes (a leaf: imports nothing else of ringscan);
- :mod:`~ringscan.pipeline.geometry`: host-side rig geometry (OpenCV);
- :mod:`~ringscan.pipeline.codecs`: frames of every codec, decode + sampling;
- :mod:`~ringscan.pipeline.reconstruct`, :mod:`~ringscan.pipeline.simulate`,
  :mod:`~ringscan.pipeline.preview`: one view / a scan / live; the virtual rig
  and its truth; offscreen rendering and heat maps;
- :mod:`~ringscan.pipeline.fusion`, :mod:`~ringscan.pipeline.evaluate`: turntable
  and multi-pose fusion, meshing; accuracy against truth, the ring-count sweep;
- :mod:`~ringscan.pipeline.batch`: many scans.

The most used functions are re-exported here and imported on first use (so
``import ringscan.pipeline.formats`` does not load Warp or Open3D)::

    from ringscan.pipeline import reconstruct_scan, read_ply
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    # The re-exports as plain imports, for import-linter (which reads imports under
    # TYPE_CHECKING too: a module that takes a name from here depends on where it
    # lives) and for type checkers. At run time __getattr__ loads them on first use.
    from ringscan.pipeline.batch import batch_reconstruct
    from ringscan.pipeline.evaluate import evaluate_recon, run_sweep
    from ringscan.pipeline.formats import (
        FormatError,
        RingscanError,
        load_rig,
        load_scan,
        parse_patterns,
        read_cloud,
        read_mesh,
        read_ply,
        write_ply,
    )
    from ringscan.pipeline.fusion import fuse_and_mesh, fuse_poses, fuse_views, mesh_cloud
    from ringscan.pipeline.reconstruct import LiveReconstructor, ReconstructSettings, reconstruct_scan, reconstruct_view
    from ringscan.pipeline.simulate import load_truth, simulate_scan

# name -> module; the same names as the TYPE_CHECKING imports above (a test checks it)
_EXPORTS = {
    "reconstruct_scan": "ringscan.pipeline.reconstruct",
    "reconstruct_view": "ringscan.pipeline.reconstruct",
    "ReconstructSettings": "ringscan.pipeline.reconstruct",
    "LiveReconstructor": "ringscan.pipeline.reconstruct",
    "simulate_scan": "ringscan.pipeline.simulate",
    "load_truth": "ringscan.pipeline.simulate",
    "evaluate_recon": "ringscan.pipeline.evaluate",
    "run_sweep": "ringscan.pipeline.evaluate",
    "fuse_and_mesh": "ringscan.pipeline.fusion",
    "fuse_views": "ringscan.pipeline.fusion",
    "fuse_poses": "ringscan.pipeline.fusion",
    "mesh_cloud": "ringscan.pipeline.fusion",
    "batch_reconstruct": "ringscan.pipeline.batch",
    "load_scan": "ringscan.pipeline.formats",
    "load_rig": "ringscan.pipeline.formats",
    "parse_patterns": "ringscan.pipeline.formats",
    "read_ply": "ringscan.pipeline.formats",
    "write_ply": "ringscan.pipeline.formats",
    "read_cloud": "ringscan.pipeline.formats",
    "read_mesh": "ringscan.pipeline.formats",
    "FormatError": "ringscan.pipeline.formats",
    "RingscanError": "ringscan.pipeline.formats",
}

__all__ = sorted(_EXPORTS)


def __getattr__(name: str):
    mod = _EXPORTS.get(name)
    if mod is None:
        raise AttributeError(f"module 'ringscan.pipeline' has no attribute {name!r}")
    value = getattr(importlib.import_module(mod), name)
    globals()[name] = value
    return value


def __dir__():
    return sorted(set(globals()) | set(_EXPORTS))
