"""Point clouds made worth looking at: shaded by estimated normals, coloured by a
field, and a single view's cloud seen from the camera that took it.

A bare point cloud renders in one flat colour (nothing to shade it by), from a
viewpoint chosen for the bounding box: a real scan then reads as a dark blob.
These helpers give the renderer what it needs:

- :func:`shade_cloud`: normals estimated (k nearest neighbours) and turned toward
  the viewer, so both renderers shade the points (headlight Lambert);
- :func:`cloud_field`: per-point values to colour by (height, or a PLY property
  such as ``confidence``), aligned with the cloud :func:`render.read_geometry` reads;
- :func:`own_camera`: for a view's PLY in a reconstruction folder, the rig's camera
  (from its report.json), so the render looks like the camera's photo.
"""

from __future__ import annotations

import logging
import os
from pathlib import Path

import numpy as np

from ringscan.pipeline.formats.atomic import read_json
from ringscan.pipeline.formats.errors import FormatError
from ringscan.pipeline.formats.ply import read_ply
from ringscan.pipeline.formats.rig import parse_rig

log = logging.getLogger(__name__)

__all__ = ["CLOUD_FIELDS", "OwnCamera", "shade_cloud", "cloud_field", "own_camera"]

CLOUD_FIELDS = ("height", "confidence", "rho", "ring", "view")
"""Fields a cloud can be coloured by (height: z; the others: the PLY property)."""
NORMAL_NEIGHBOURS = 20
"""Neighbours of the plane fitted for a point's normal."""


def shade_cloud(cloud, *, towards=None, k: int = NORMAL_NEIGHBOURS):
    """Give a point cloud normals (in place) where it has none, turned toward
    ``towards`` (a 3-vector: the camera centre; default: away from the cloud's
    centre), so that it renders shaded. Returns the cloud."""
    import open3d as o3d

    if cloud.has_normals() or len(cloud.points) < 3:
        return cloud
    cloud.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(knn=min(k, len(cloud.points))))
    pts = np.asarray(cloud.points)
    n = np.asarray(cloud.normals)
    ref = np.asarray(towards, float) if towards is not None else None
    out = (ref - pts) if ref is not None else (pts - pts.mean(axis=0))
    flip = np.einsum("ij,ij->i", n, out) < 0
    n[flip] *= -1
    cloud.normals = o3d.utility.Vector3dVector(n)
    return cloud


def cloud_field(path: str | os.PathLike, field: str, cloud) -> np.ndarray:
    """Per-point values of ``field`` for the cloud read from ``path``.

    ``height`` is the z coordinate; any other field is the PLY vertex property of
    that name, for the points with finite coordinates (those read_geometry keeps).

    Raises:
        FormatError: naming the file: the property is absent, or its points do not
            match the cloud's.
    """
    if field == "height":
        return np.asarray(cloud.points)[:, 2].astype(np.float64)
    path = Path(path)
    if path.suffix.lower() != ".ply":
        raise FormatError(path, f"--color-by {field}: only a PLY carries per-point {field}")
    ply = read_ply(path)
    if field not in ply:
        have = ", ".join(k for k in ply if k not in ("x", "y", "z")) or "none"
        raise FormatError(path, f"--color-by {field}: no vertex property {field!r} (it has: {have})")
    xyz = np.stack([ply["x"], ply["y"], ply["z"]], -1)
    finite = np.all(np.isfinite(xyz), axis=1)
    vals = np.asarray(ply[field], np.float64)[finite]
    if len(vals) != len(cloud.points):
        raise FormatError(path, f"--color-by {field}: {len(vals)} values for {len(cloud.points)} points")
    return vals


class OwnCamera:
    """The camera that took a view: intrinsics, world -> camera extrinsics, size."""

    def __init__(self, K: np.ndarray, E: np.ndarray, width: int, height: int, view: str, turntable_deg: float):
        self.K, self.E, self.width, self.height = K, E, width, height
        self.view, self.turntable_deg = view, turntable_deg

    def centre(self) -> np.ndarray:
        """The camera centre in world coordinates (mm)."""
        return -self.E[:3, :3].T @ self.E[:3, 3]

    def scaled(self, width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
        """(K, E) for a render of ``width`` x ``height``: the same view, rescaled."""
        sx, sy = width / self.width, height / self.height
        K = self.K.copy()
        K[0, 0] *= sx
        K[0, 2] = (K[0, 2] + 0.5) * sx - 0.5
        K[1, 1] *= sy
        K[1, 2] = (K[1, 2] + 0.5) * sy - 0.5
        return K, self.E


def own_camera(ply_path: str | os.PathLike) -> OwnCamera | None:
    """The camera of a view's PLY written by ``reconstruct`` (report.json beside it
    names it), or None for any other file. Lens distortion is left out (a pinhole
    render of the undistorted view)."""
    p = Path(ply_path)
    report = p.parent / "report.json"
    if p.suffix.lower() != ".ply" or not report.is_file():
        return None
    try:
        rep = read_json(report)
        views = [v for v in rep.get("views", []) if isinstance(v, dict) and v.get("ply") == p.name]
        if not views or not isinstance(rep.get("rig"), dict):
            return None
        cam = parse_rig(rep["rig"], source=report).camera
    except (FormatError, ValueError, TypeError) as e:
        log.info("%s: no camera of its own (%s)", p, e)
        return None
    E = np.eye(4)
    E[:3, :3], E[:3, 3] = cam.R, cam.t
    return OwnCamera(np.asarray(cam.K, float), E, int(cam.width), int(cam.height), str(views[0].get("name")),
                     float(views[0].get("turntable_deg", 0.0)))


BOARD_UNITS = "board units"
"""The length unit of a scan whose calibration stated none (an OpenCV file imported without --units):
whatever the board was measured in, not known to be mm."""


def length_unit(ply_path: str | os.PathLike) -> str:
    """The unit of a cloud's coordinates: ``"mm"``, or :data:`BOARD_UNITS` for a view's PLY of a scan
    imported from a calibration that states no units (scan.json ``imported.units.source`` "assumed");
    a file with nothing beside it to say otherwise is in mm (ringscan writes mm)."""
    report = Path(ply_path).parent / "report.json"
    try:
        scan = read_json(report).get("scan") if report.is_file() else None
        units = (read_json(Path(scan) / "scan.json").get("imported") or {}).get("units") if scan else None
    except (FormatError, ValueError, TypeError, OSError) as e:
        log.info("%s: its units unknown (%s): mm", ply_path, e)
        return "mm"
    return BOARD_UNITS if isinstance(units, dict) and units.get("source") == "assumed" else "mm"
