"""Fusion's inputs: reconstruction folders (``report.json`` plus one PLY per view),
read as turntable views, or scan folders reconstructed first; one folder fused, or
several poses of one object fused and aligned."""

from __future__ import annotations

import logging
import os
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from ringscan.pipeline.formats.atomic import read_json
from ringscan.pipeline.formats.errors import FormatError
from ringscan.pipeline.formats.ply import read_ply
from ringscan.pipeline.formats.rig import Rig, load_rig, parse_rig
from ringscan.pipeline.fusion.poses import MultiPoseResult, PoseSettings, fuse_poses
from ringscan.pipeline.fusion.turntable import REPORT_NAME, FuseResult, FuseSettings, FusionView, fuse_views
from ringscan.pipeline.reconstruct.scan import reconstruct_scan

log = logging.getLogger(__name__)

__all__ = ["load_recon", "recon_folder", "fuse_recon", "fuse_recons"]


def load_recon(recon_dir: str | os.PathLike) -> tuple[list[FusionView], Rig | None, dict]:
    """Read a reconstruction folder: ``report.json`` and one PLY per view.

    Returns:
        (views, rig, report): the views in the world frame, the rig from the report
        (None if it has none) and the report dictionary itself.

    Raises:
        FormatError: naming the file and field that is missing or wrong.
    """
    recon_dir = Path(recon_dir)
    report_path = recon_dir / REPORT_NAME
    report = read_json(report_path)
    rig = None
    if report.get("rig") is not None:
        rig_entry = report["rig"]
        if isinstance(rig_entry, str):
            rig = load_rig(recon_dir / rig_entry)
        else:
            rig = parse_rig(rig_entry, source=f"{report_path}: rig")
    entries = report.get("views")
    if not isinstance(entries, list) or not entries:
        raise FormatError(report_path, "views: missing or empty")
    views = [_read_view(recon_dir, report_path, i, entry, rig) for i, entry in enumerate(entries)]
    return views, rig, report


def _read_view(recon_dir: Path, report_path: Path, i: int, entry, rig: Rig | None) -> FusionView:
    """View ``i`` of a reconstruction report: its report entry checked, its PLY read."""
    where = f"views[{i}]"
    if not isinstance(entry, dict):
        raise FormatError(report_path, f"{where}: expected an object")
    name = entry.get("name", f"view_{i:03d}")
    ply = entry.get("ply")
    if not isinstance(ply, str):
        raise FormatError(report_path, f"{where}.ply: missing or not a string")
    turntable_deg = entry.get("turntable_deg", 0.0)
    if isinstance(turntable_deg, bool) or not isinstance(turntable_deg, (int, float)):
        raise FormatError(report_path, f"{where}.turntable_deg: expected a number, got {turntable_deg!r}")
    centre = entry.get("camera_center")
    if centre is None and rig is not None:
        centre = rig.camera.center.tolist()
    try:
        centre = np.asarray(centre, dtype=np.float64)
    except (TypeError, ValueError):
        centre = None
    if centre is None or centre.shape != (3,):
        raise FormatError(report_path, f"{where}.camera_center: expected 3 numbers (or a rig with a camera)")
    fields = read_ply(recon_dir / ply)
    for k in ("x", "y", "z"):
        if k not in fields:
            raise FormatError(recon_dir / ply, f"vertex property {k!r} missing")
    points = np.stack([fields["x"], fields["y"], fields["z"]], axis=1).astype(np.float64)
    normals = None
    if all(k in fields for k in ("nx", "ny", "nz")):
        normals = np.stack([fields["nx"], fields["ny"], fields["nz"]], axis=1).astype(np.float64)
    confidence = fields["confidence"].astype(np.float64) if "confidence" in fields else None
    sigma = fields["sigma"].astype(np.float64) if "sigma" in fields else None
    return FusionView(name=str(name), points=points, turntable_deg=float(turntable_deg), camera_center=centre,
                      normals=normals, confidence=confidence, sigma=sigma)


def recon_folder(path: str | os.PathLike, *, work_dir: str | os.PathLike | None = None, device: str | None = None,
                 progress: bool = False) -> Path:
    """The reconstruction folder for ``path``.

    A folder with ``report.json`` is returned as it is. A scan folder (with
    ``scan.json``) is reconstructed first, into ``work_dir`` (required then), with
    :func:`ringscan.pipeline.reconstruct.reconstruct_scan`.

    Raises:
        FormatError: ``path`` is neither.
        ValueError: a scan folder without ``work_dir``.
    """
    path = Path(path)
    if (path / REPORT_NAME).is_file():
        return path
    if (path / "scan.json").is_file():
        if work_dir is None:
            raise ValueError(f"{path} is a scan folder: give a folder to reconstruct it into")
        log.info("reconstructing scan %s into %s", path, work_dir)
        reconstruct_scan(path, work_dir, device=device, progress=progress)
        return Path(work_dir)
    if not path.exists():
        raise FormatError(path, "not found")
    raise FormatError(path, f"neither a reconstruction folder ({REPORT_NAME}) nor a scan folder (scan.json)")


def fuse_recon(path: str | os.PathLike, *, settings: FuseSettings = FuseSettings(), rig: Rig | None = None,
               work_dir: str | os.PathLike | None = None, device: str | None = None,
               progress: bool = False) -> FuseResult:
    """Fuse a reconstruction folder (``report.json`` + per-view PLYs) or a scan folder.

    Args:
        path: the reconstruction folder, or a scan folder (reconstructed first into
            ``work_dir``, see :func:`recon_folder`).
        settings: fusion settings.
        rig: use this rig instead of the one in the report (e.g. a corrected axis).
        work_dir: where a scan folder is reconstructed.
        device: Warp device for that reconstruction.
        progress: show progress bars.
    """
    folder = recon_folder(path, work_dir=work_dir, device=device, progress=progress)
    views, report_rig, _ = load_recon(folder)
    return fuse_views(views, rig if rig is not None else report_rig, settings=settings, progress=progress)


def fuse_recons(paths: Sequence, *, settings: FuseSettings = FuseSettings(),
                pose_settings: PoseSettings = PoseSettings(), work_dir: str | os.PathLike | None = None,
                device: str | None = None, progress: bool = False) -> MultiPoseResult:
    """Fuse several scans of one object in different poses (flip and rescan).

    Each path (a reconstruction folder or a scan folder, see :func:`fuse_recon`) is
    fused on its own, then :func:`fuse_poses` aligns them to the first and merges.
    Scan folders are reconstructed into ``work_dir/pose_<i>``.

    Raises:
        AlignmentError: naming the source whose alignment failed.
    """
    if isinstance(paths, (str, bytes, os.PathLike)) or not isinstance(paths, Sequence) or len(paths) == 0:
        raise ValueError("paths: expected a non-empty sequence of folders")
    results = []
    for i, p in enumerate(paths):
        pose_dir = None if work_dir is None else Path(work_dir) / f"pose_{i}"
        log.info("pose %d: fusing %s", i, p)
        results.append(fuse_recon(p, settings=settings, work_dir=pose_dir, device=device, progress=progress))
    return fuse_poses(results, names=[str(p) for p in paths], settings=pose_settings, progress=progress)
