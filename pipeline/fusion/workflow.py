"""The fuse-and-mesh workflow behind ``ringscan fuse`` and ``ringscan demo``: read
reconstruction folders (reconstructing scan folders first), fuse turntable views and
poses, mesh, compare with the truth when known, write the mesh, a preview PNG and
``fuse_report.json``.
"""

from __future__ import annotations

import dataclasses
import logging
import os
import time
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from ringscan.pipeline.formats.atomic import (
    atomic_write_json,
    check_no_overwrite,
    check_output_folder,
    read_json,
    remove_stale_temporaries,
)
from ringscan.pipeline.formats.errors import FormatError
from ringscan.pipeline.formats.meshes import MESH_FORMATS, _ext, open3d_lib, read_mesh, write_cloud, write_mesh
from ringscan.pipeline.formats.ply import read_ply
from ringscan.pipeline.formats.progress import progress_step
from ringscan.pipeline.formats.rig import Rig, load_rig, parse_rig
from ringscan.pipeline.formats.scan import load_scan
from ringscan.pipeline.fusion.mesh import (
    MIN_MESH_POINTS,
    MeshResult,
    MeshSettings,
    check_mesh_settings,
    compare_to_truth,
    drop_unusable_points,
    poisson_mesh,
)
from ringscan.pipeline.fusion.poses import MultiPoseResult, PoseSettings, fuse_poses
from ringscan.pipeline.fusion.tsdf import tsdf_mesh
from ringscan.pipeline.fusion.turntable import REPORT_NAME, FuseResult, FuseSettings, FusionView, fuse_views
from ringscan.pipeline.preview.render import render_to_png
from ringscan.pipeline.reconstruct.scan import reconstruct_scan, scan_inputs

log = logging.getLogger(__name__)

__all__ = ["load_recon", "recon_folder", "fuse_recon", "fuse_recons", "FUSE_REPORT_FORMAT", "fuse_and_mesh", "mesh_cloud", "mesh_fused",
           "load_truth_mesh"]






def load_recon(recon_dir: str | os.PathLike) -> tuple[list[FusionView], Rig | None, dict]:
    """Read a reconstruction folder: ``report.json`` and one PLY per view.

    Returns:
        (views, rig, report): the views in the world frame, the rig from the report
        (None if it has none) and the report dictionary itself.

    Raises:
        FormatError: naming the file and field that is missing or wrong.
    """
    recon_dir = Path(recon_dir)
    rpath = recon_dir / REPORT_NAME
    report = read_json(rpath)
    rig = None
    if report.get("rig") is not None:
        rig_d = report["rig"]
        if isinstance(rig_d, str):

            rig = load_rig(recon_dir / rig_d)
        else:
            rig = parse_rig(rig_d, source=f"{rpath}: rig")
    vlist = report.get("views")
    if not isinstance(vlist, list) or not vlist:
        raise FormatError(rpath, "views: missing or empty")
    views = []
    for i, vd in enumerate(vlist):
        where = f"views[{i}]"
        if not isinstance(vd, dict):
            raise FormatError(rpath, f"{where}: expected an object")
        name = vd.get("name", f"view_{i:03d}")
        ply = vd.get("ply")
        if not isinstance(ply, str):
            raise FormatError(rpath, f"{where}.ply: missing or not a string")
        th = vd.get("turntable_deg", 0.0)
        if isinstance(th, bool) or not isinstance(th, (int, float)):
            raise FormatError(rpath, f"{where}.turntable_deg: expected a number, got {th!r}")
        cc = vd.get("camera_center")
        if cc is None and rig is not None:
            cc = rig.camera.center.tolist()
        try:
            cc = np.asarray(cc, dtype=np.float64)
        except (TypeError, ValueError):
            cc = None
        if cc is None or cc.shape != (3,):
            raise FormatError(rpath, f"{where}.camera_center: expected 3 numbers (or a rig with a camera)")
        f = read_ply(recon_dir / ply)
        for k in ("x", "y", "z"):
            if k not in f:
                raise FormatError(recon_dir / ply, f"vertex property {k!r} missing")
        pts = np.stack([f["x"], f["y"], f["z"]], axis=1).astype(np.float64)
        nrm = None
        if all(k in f for k in ("nx", "ny", "nz")):
            nrm = np.stack([f["nx"], f["ny"], f["nz"]], axis=1).astype(np.float64)
        conf = f["confidence"].astype(np.float64) if "confidence" in f else None
        views.append(FusionView(name=str(name), points=pts, turntable_deg=float(th), camera_center=cc,
                               normals=nrm, confidence=conf))
    return views, rig, report


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
    views, rep_rig, _ = load_recon(folder)
    return fuse_views(views, rig if rig is not None else rep_rig, settings=settings, progress=progress)


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
        wd = None if work_dir is None else Path(work_dir) / f"pose_{i}"
        log.info("pose %d: fusing %s", i, p)
        results.append(fuse_recon(p, settings=settings, work_dir=wd, device=device, progress=progress))
    return fuse_poses(results, names=[str(p) for p in paths], settings=pose_settings, progress=progress)


FUSE_REPORT_FORMAT = "ringscan.fuse/1"


def fuse_and_mesh(recon_dir, out_dir: str | os.PathLike, *, fuse_settings=None,
                  mesh_settings: MeshSettings = MeshSettings(), formats=(".ply",), preview: bool = True,
                  rig=None, truth=None, device: str | None = None, progress: bool = False,
                  pose_settings=None) -> dict:
    """Fuse a reconstruction folder (or a scan folder), mesh it, write everything.

    Writes into ``out_dir``: ``fused.ply`` (the fused cloud), ``mesh.<ext>`` for each
    of ``formats`` (ply, obj, stl), ``preview.png`` (when ``preview``; see
    :mod:`ringscan.pipeline.preview`) and ``fuse_report.json`` (per-view residuals,
    mesh checks, resolved settings, and the figures against ``truth`` when given).
    A ``mesh.<ext>`` in another format (or a ``preview.png`` with ``preview`` off)
    that an earlier run left in ``out_dir`` is removed, and named in the report's
    ``outputs.removed``: the folder then holds what this run made, nothing older.
    A scan folder is reconstructed first into ``out_dir/recon``.

    ``recon_dir`` may also be a list of folders: scans of the same object in several
    poses (flip and rescan). The first is the reference pose; each is fused on its
    own, the others are aligned to it (:func:`ringscan.pipeline.fusion.poses.fuse_poses`,
    with ``pose_settings``) and everything is merged in its object frame. Scan
    folders are then reconstructed into ``out_dir/recon/pose_<i>``; the report's
    ``fusion.poses`` holds each pose's transform, fitness and inlier RMSE, and
    ``fused.ply``'s ``view`` property is the pose index.

    Args:
        truth: a truth mesh (``o3d.geometry.TriangleMesh``, a mesh file, or a
            simulated scan folder whose ``truth/object.ply`` is used) to measure the
            mesh against with :func:`compare_to_truth`.

    Returns:
        The report dictionary (also written to ``fuse_report.json``).
    """

    fuse_settings = FuseSettings() if fuse_settings is None else fuse_settings
    pose_settings = PoseSettings() if pose_settings is None else pose_settings
    sources = [recon_dir] if isinstance(recon_dir, (str, bytes, os.PathLike)) else list(recon_dir)
    if not sources:
        raise ValueError("no source folder given")
    multi = len(sources) > 1
    if multi and rig is not None:
        raise ValueError("rig: a replacement rig applies to a single source only")
    check_mesh_settings(mesh_settings)
    out_dir = check_output_folder(out_dir, what="fusion's output folder")
    fmts = []
    for f in formats:
        f = str(f).lower()
        f = f if f.startswith(".") else f".{f}"
        _ext(Path("mesh" + f), MESH_FORMATS)
        fmts.append(f)
    outputs = [out_dir / n for n in ("fused.ply", "preview.png", "fuse_report.json")]
    input_files = ([q for src in sources for q in _source_files(Path(src))]
                   + ([Path(truth)] if isinstance(truth, (str, os.PathLike)) else []))
    check_no_overwrite([*outputs, *(out_dir / f"mesh{f}" for f in fmts)], input_files)
    remove_stale_temporaries(out_dir)
    truth_mesh = load_truth_mesh(truth) if truth is not None else None
    t0 = time.perf_counter()
    if multi:
        fused = fuse_recons(sources, settings=fuse_settings, pose_settings=pose_settings, work_dir=out_dir / "recon",
                            device=device, progress=progress)
    else:
        fused = fuse_recon(sources[0], settings=fuse_settings, rig=rig, work_dir=out_dir / "recon", device=device,
                           progress=progress)
    t_fuse = time.perf_counter() - t0
    # TSDF from several poses integrates the merged cloud (virtual views), not the per-view depth maps.
    with progress_step(f"{mesh_settings.method} meshing", enabled=progress):
        mres = mesh_cloud(fused.cloud, settings=mesh_settings) if multi else mesh_fused(fused, settings=mesh_settings)
    out_dir.mkdir(parents=True, exist_ok=True)
    write_cloud(out_dir / "fused.ply", fused.cloud, view=fused.point_view, confidence=fused.point_confidence)
    outputs = {"cloud": "fused.ply", "meshes": []}
    for f in fmts:
        write_mesh(out_dir / f"mesh{f}", mres.mesh)
        outputs["meshes"].append(f"mesh{f}")
    if preview:
        with progress_step("rendering preview.png", enabled=progress):
            res = render_to_png([mres.mesh], out_dir / "preview.png")
        outputs["preview"] = "preview.png"
        outputs["preview_renderer"] = res.renderer
    # A rerun into the same folder writes exactly what it is asked for: the earlier
    # run's meshes in other formats (and its preview, with preview off) would sit
    # beside the new mesh as if made from it. They are removed and named.
    written = {out_dir / "fused.ply", out_dir / "fuse_report.json", *(out_dir / m for m in outputs["meshes"]),
               *([out_dir / "preview.png"] if preview else [])}
    inputs = {Path(q).resolve() for q in input_files}
    removed = []
    for stale in [*(out_dir / f"mesh{f}" for f in MESH_FORMATS), out_dir / "preview.png"]:
        if stale not in written and stale.is_file() and stale.resolve() not in inputs:
            stale.unlink()
            removed.append(stale.name)
            log.info("removed %s, left by an earlier run (not asked for this time)", stale)
    if removed:
        outputs["removed"] = removed
    rep = {"format": FUSE_REPORT_FORMAT, "source": str(Path(sources[0]).resolve()),
           "fusion": fused.report(), "mesh": {"method": mres.method, "watertight": mres.watertight, **mres.info},
           "settings": {"fuse": dataclasses.asdict(fuse_settings), "mesh": dataclasses.asdict(mesh_settings)},
           "outputs": outputs}
    if multi:
        rep["sources"] = [str(Path(p).resolve()) for p in sources]
        rep["settings"]["poses"] = dataclasses.asdict(pose_settings)
    if truth_mesh is not None:
        rep["truth"] = compare_to_truth(mres.mesh, truth_mesh)
    rep["seconds"] = {"fuse": round(t_fuse, 3), "total": round(time.perf_counter() - t0, 3)}
    atomic_write_json(out_dir / "fuse_report.json", rep)
    return rep


def _source_files(src: Path) -> list[Path]:
    """The files of a fusion source: a reconstruction folder's report and clouds, or a scan's files."""
    if (src / REPORT_NAME).is_file():
        return [src / REPORT_NAME, *src.glob("*.ply")]
    if (src / "scan.json").is_file():
        try:
            return scan_inputs(load_scan(src, check_files=False, allow_incomplete=True))
        except FormatError:
            return [src / "scan.json"]
    return []


def load_truth_mesh(truth):
    """The truth mesh of ``--truth``: an ``o3d.geometry.TriangleMesh``, a mesh file
    (PLY/OBJ/STL), or a simulated scan folder (its ``truth.mesh`` in scan.json, the
    object in its own frame).

    Raises:
        FormatError: naming the file: unreadable, or a scan without a truth mesh.
    """
    o3d = open3d_lib()
    if isinstance(truth, o3d.geometry.TriangleMesh):
        return truth
    p = Path(truth)
    if p.is_dir():

        t = read_json(p / "scan.json").get("truth")
        if not isinstance(t, dict) or not isinstance(t.get("mesh"), str):
            raise FormatError(p / "scan.json", "truth.mesh: this scan has no ground truth mesh")
        p = p / t["mesh"]
    return read_mesh(p)


def mesh_cloud(cloud, *, settings: MeshSettings = MeshSettings()) -> MeshResult:
    """Mesh a bare oriented cloud with ``settings.method``.

    Points that meshing cannot use (NaN, infinite, beyond +-``MAX_COORDINATE_MM``)
    are dropped first and counted in the result's ``info["dropped_points"]``.

    Raises:
        ValueError: fewer than ``MIN_MESH_POINTS`` usable points.
    """
    check_mesh_settings(settings)
    n_in = len(cloud.points)
    cloud, dropped = drop_unusable_points(cloud)
    if len(cloud.points) < MIN_MESH_POINTS:
        raise ValueError(f"the cloud has {len(cloud.points)} usable points (of {n_in}; {dropped['non_finite']} "
                         f"non-finite, {dropped['out_of_range']} out of range): too few to mesh "
                         f"(need at least {MIN_MESH_POINTS})")
    res = tsdf_mesh(cloud, settings=settings) if settings.method == "tsdf" else poisson_mesh(cloud, settings=settings)
    res.info["dropped_points"] = dropped
    return res


def mesh_fused(result, *, settings: MeshSettings = MeshSettings()) -> MeshResult:
    """Mesh a :class:`~ringscan.pipeline.fusion.turntable.FuseResult`: Poisson on its fused
    cloud, or TSDF from its views' depth maps."""
    check_mesh_settings(settings)
    if settings.method == "tsdf":
        return tsdf_mesh(result, settings=settings)
    return poisson_mesh(result.cloud, settings=settings)
