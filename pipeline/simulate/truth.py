"""The virtual rig's ground truth, written next to a simulated scan (``truth/``):
the placed mesh per view, depth and lit masks; :func:`load_truth` reads it back.
"""

from __future__ import annotations

import logging
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ringscan.pipeline.formats.atomic import atomic_path, atomic_write_bytes
from ringscan.pipeline.formats.errors import FormatError
from ringscan.pipeline.formats.images import read_image
from ringscan.pipeline.formats.limits import check_image_header
from ringscan.pipeline.formats.rig import Turntable
from ringscan.pipeline.formats.scan import Scan, check_truth, load_scan
from ringscan.pipeline.simulate.virtual_rig import _turn

log = logging.getLogger(__name__)

__all__ = ["TRUTH_DIR", "Truth", "load_truth"]


TRUTH_DIR = "truth"


@dataclass(frozen=True)
class Truth:
    """Ground truth of a simulated scan (see :func:`load_truth`)."""

    folder: Path
    """The scan folder."""
    vertices: np.ndarray
    """(N, 3) float64 mesh vertices in the object frame (= world frame at angle 0)."""
    faces: np.ndarray
    """(M, 3) int32 triangles (empty for the ``plane`` scene)."""
    reference_plane_z: float
    """z of the reference plane (0)."""
    turntable: Turntable | None
    """The rig's turntable (None: single pose)."""
    views: dict
    """View name -> {"depth": relative path, "lit": relative path}, and ``camera2``: the same for
    camera 2 (a two-camera scan)."""
    settings: dict
    """The render settings used."""
    scene: str = ""
    """Scene name or mesh file stem."""

    def mesh_at(self, turntable_deg: float) -> tuple[np.ndarray, np.ndarray]:
        """The mesh in the world frame of a view at ``turntable_deg``: (vertices, faces)."""
        R, t = _turn(self.turntable, turntable_deg)
        return self.vertices @ R.T + t, self.faces

    def _file(self, view: str, key: str, camera: int = 1) -> Path:
        if view not in self.views:
            raise ValueError(f"truth: no view {view!r} (have {', '.join(self.views) or 'none'})")
        v = self.views[view]
        if camera == 2:
            if "camera2" not in v:
                raise ValueError(f"truth: view {view!r} has no camera 2 (a one-camera scan)")
            v = v["camera2"]
        elif camera != 1:
            raise ValueError(f"truth: camera must be 1 or 2, got {camera!r}")
        return self.folder / v[key]

    def depth(self, view: str, camera: int = 1) -> np.ndarray:
        """(H, W) float32 camera-frame depth of a view (mm) seen by camera 1 or 2, NaN where nothing was hit."""
        import cv2

        p = self._file(view, "depth", camera)
        if not p.is_file():
            raise FormatError(p, "truth depth file not found")
        check_image_header(p)
        d = cv2.imread(str(p), cv2.IMREAD_UNCHANGED)
        if d is None or d.dtype != np.float32 or d.ndim != 2:
            raise FormatError(p, "not a single-channel float32 TIFF")
        return d

    def lit(self, view: str, camera: int = 1) -> np.ndarray:
        """(H, W) bool: the pixel's centre (of camera 1 or 2) sees a point lit by the projector image."""

        return read_image(self._file(view, "lit", camera)) > 0


def _write_mesh(path: Path, vertices: np.ndarray, faces: np.ndarray) -> None:
    """Binary little-endian PLY mesh (double x, y, z; int triangles) that Open3D and
    MeshLab read; written by hand because Open3D refuses an empty mesh (the plane)."""
    v = np.ascontiguousarray(vertices, "<f8").reshape(-1, 3)
    f = np.asarray(faces, np.int64).reshape(-1, 3)
    header = ("ply\nformat binary_little_endian 1.0\n"
              "comment ringscan virtual rig ground truth: object frame (= world at turntable 0), mm\n"
              f"element vertex {len(v)}\nproperty double x\nproperty double y\nproperty double z\n"
              f"element face {len(f)}\nproperty list uchar int vertex_indices\nend_header\n")
    rec = np.empty(len(f), dtype=[("n", "u1"), ("i", "<i4", (3,))])
    rec["n"] = 3
    rec["i"] = f
    atomic_write_bytes(path, header.encode("ascii") + v.tobytes() + rec.tobytes())


def _mesh_is_empty(path: Path) -> bool:
    head = path.read_bytes()[:4096]
    end = head.find(b"end_header")
    if not head.startswith(b"ply") or end < 0:
        raise FormatError(path, "not a PLY file")
    for ln in head[:end].decode("ascii", "replace").splitlines():
        parts = ln.split()
        if parts[:2] == ["element", "vertex"] and len(parts) == 3:
            return parts[2] == "0"
    raise FormatError(path, "PLY header has no vertex element")


def _write_depth(path: Path, depth: np.ndarray) -> None:
    import cv2

    with atomic_path(path) as tmp:
        if not cv2.imwrite(str(tmp), np.ascontiguousarray(depth, np.float32)):
            raise FormatError(path, "OpenCV could not write the float32 TIFF")


def load_truth(scan: Scan | str | os.PathLike) -> Truth:
    """Read the ground truth of a simulated scan (a :class:`Scan` or its folder).

    Raises:
        FormatError: the scan has no ``truth`` block, or a truth file is missing or bad.
    """
    import open3d as o3d

    if not isinstance(scan, Scan):
        scan = load_scan(scan, check_files=False, allow_incomplete=True)
    t = check_truth(scan)
    mp = scan.folder / t["mesh"]
    if not mp.is_file():
        raise FormatError(mp, "truth mesh not found (listed in scan.json truth.mesh)")
    if _mesh_is_empty(mp):
        vertices, faces = np.zeros((0, 3)), np.zeros((0, 3), np.int32)
    else:
        m = o3d.io.read_triangle_mesh(str(mp))
        vertices = np.asarray(m.vertices, np.float64).copy()
        faces = np.asarray(m.triangles, np.int64).astype(np.int32)
        if faces.shape[0] == 0:
            raise FormatError(mp, "truth mesh holds no triangles")
    return Truth(folder=scan.folder, vertices=vertices, faces=faces, reference_plane_z=t["reference_plane_z"],
                 turntable=scan.rig.turntable, views=t["views"], settings=t["settings"], scene=t["scene"])
