"""The fuse-and-mesh workflow behind ``ringscan fuse`` and ``ringscan demo``: check
the outputs, fuse the sources (:mod:`.recon`), mesh (:mod:`.meshing`), compare with
the truth when known, write the fused cloud, the meshes, a preview PNG and
``fuse_report.json``.
"""

from __future__ import annotations

import dataclasses
import logging
import os
import time
from pathlib import Path

from ringscan.pipeline.formats.atomic import (
    atomic_write_json,
    check_no_overwrite,
    check_output_folder,
    remove_stale_temporaries,
)
from ringscan.pipeline.formats.errors import FormatError
from ringscan.pipeline.formats.meshes import MESH_FORMATS, _ext, open3d_lib, read_mesh, write_cloud, write_mesh
from ringscan.pipeline.formats.progress import progress_step
from ringscan.pipeline.formats.scan import check_truth, load_scan
from ringscan.pipeline.fusion.mesh import MeshResult, MeshSettings, check_mesh_settings, compare_to_truth
from ringscan.pipeline.fusion.meshing import mesh_cloud, mesh_fused
from ringscan.pipeline.fusion.poses import PoseSettings
from ringscan.pipeline.fusion.recon import fuse_recon, fuse_recons
from ringscan.pipeline.fusion.turntable import REPORT_NAME, FuseSettings
from ringscan.pipeline.preview.render import render_to_png
from ringscan.pipeline.reconstruct.scan import scan_inputs

log = logging.getLogger(__name__)

__all__ = ["FUSE_REPORT_FORMAT", "fuse_and_mesh", "load_truth_mesh"]


FUSE_REPORT_FORMAT = "ringscan.fuse/1"


def fuse_and_mesh(recon_dir, out_dir: str | os.PathLike, *, fuse_settings=None,
                  mesh_settings: MeshSettings = MeshSettings(), formats=(".ply",), preview: bool = True,
                  rig=None, truth=None, device: str | None = None, progress: bool = False,
                  pose_settings=None, preview_scale_bar: bool = False,
                  preview_view=None) -> dict:
    """Fuse a reconstruction folder (or a scan folder), mesh it, write everything.

    Writes into ``out_dir``: ``fused.ply`` (the fused cloud), ``mesh.<ext>`` for each
    of ``formats`` (ply, obj, stl), ``preview.png`` (when ``preview``; see
    :mod:`ringscan.pipeline.preview`) and ``fuse_report.json`` (per-view residuals,
    mesh checks, resolved settings, and the figures against ``truth`` when given).
    ``preview_scale_bar`` draws a bar of a round number of millimetres on the preview
    (:func:`ringscan.pipeline.preview.render.render_to_png`; the report's
    ``outputs.preview_scale_bar_mm``); ``preview_view`` (a
    :class:`ringscan.pipeline.preview.render.ViewSettings`) frames it (None: the default view).
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

    Size: a public function (ringscan fuse's whole workflow): the source and output folders and its documented
    keyword-only options, one per user-facing setting (fusion, meshing, poses, formats, preview, rig, truth,
    device, progress); over a third of its length is their documentation, the body's steps (fusing, meshing,
    writing the outputs) are calls of their own, and the rest checks the inputs and builds the report.
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
    mesh_exts = _mesh_extensions(formats)
    fixed_outputs = [out_dir / n for n in ("fused.ply", "preview.png", "fuse_report.json")]
    input_files = ([q for src in sources for q in _source_files(Path(src))]
                   + ([Path(truth)] if isinstance(truth, (str, os.PathLike)) else []))
    check_no_overwrite([*fixed_outputs, *(out_dir / f"mesh{ext}" for ext in mesh_exts)], input_files)
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
        meshed = mesh_cloud(fused.cloud, settings=mesh_settings) if multi else mesh_fused(fused, settings=mesh_settings)
    outputs = _write_outputs(out_dir, fused, meshed, mesh_exts, preview=preview, progress=progress,
                             scale_bar=preview_scale_bar, view=preview_view)
    _remove_stale_outputs(out_dir, outputs, input_files, preview=preview)

    report = {"format": FUSE_REPORT_FORMAT, "source": str(Path(sources[0]).resolve()),
              "fusion": fused.report(),
              "mesh": {"method": meshed.method, "watertight": meshed.watertight, **meshed.info},
              "settings": {"fuse": dataclasses.asdict(fuse_settings), "mesh": dataclasses.asdict(mesh_settings)},
              "outputs": outputs}
    if multi:
        report["sources"] = [str(Path(p).resolve()) for p in sources]
        report["settings"]["poses"] = dataclasses.asdict(pose_settings)
    if truth_mesh is not None:
        report["truth"] = compare_to_truth(meshed.mesh, truth_mesh)
    report["seconds"] = {"fuse": round(t_fuse, 3), "total": round(time.perf_counter() - t0, 3)}
    atomic_write_json(out_dir / "fuse_report.json", report)
    return report


def _mesh_extensions(formats) -> list[str]:
    """The mesh file extensions asked for (``"stl"`` or ``".STL"`` -> ``".stl"``), each checked."""
    exts = []
    for f in formats:
        ext = str(f).lower()
        ext = ext if ext.startswith(".") else f".{ext}"
        _ext(Path("mesh" + ext), MESH_FORMATS)
        exts.append(ext)
    return exts


def _write_outputs(out_dir: Path, fused, meshed: MeshResult, mesh_exts: list[str], *, preview: bool,
                   progress: bool, scale_bar: bool = False, view=None) -> dict:
    """Write the fused cloud, one mesh file per extension and the preview; returns the
    report's ``outputs`` entry (file names relative to ``out_dir``)."""
    out_dir.mkdir(parents=True, exist_ok=True)
    write_cloud(out_dir / "fused.ply", fused.cloud, view=fused.point_view, confidence=fused.point_confidence,
                sigma=fused.point_sigma)
    outputs = {"cloud": "fused.ply", "meshes": []}
    for ext in mesh_exts:
        write_mesh(out_dir / f"mesh{ext}", meshed.mesh)
        outputs["meshes"].append(f"mesh{ext}")
    if preview:
        with progress_step("rendering preview.png", enabled=progress):
            rendered = render_to_png([meshed.mesh], out_dir / "preview.png", scale_bar=scale_bar,
                                     **({} if view is None else {"settings": view}))
        outputs["preview"] = "preview.png"
        outputs["preview_renderer"] = rendered.renderer
        if scale_bar:
            outputs["preview_scale_bar_mm"] = rendered.scale_bar_mm
    return outputs


def _remove_stale_outputs(out_dir: Path, outputs: dict, input_files: list[Path], *, preview: bool) -> None:
    """A rerun into the same folder holds exactly what it was asked for: the earlier
    run's meshes in other formats (and its preview, with preview off) would sit
    beside the new mesh as if made from it. They are removed and named in
    ``outputs["removed"]`` (never an input)."""
    written = {out_dir / "fused.ply", out_dir / "fuse_report.json", *(out_dir / m for m in outputs["meshes"]),
               *([out_dir / "preview.png"] if preview else [])}
    inputs = {Path(q).resolve() for q in input_files}
    removed = []
    for stale in [*(out_dir / f"mesh{ext}" for ext in MESH_FORMATS), out_dir / "preview.png"]:
        if stale not in written and stale.is_file() and stale.resolve() not in inputs:
            stale.unlink()
            removed.append(stale.name)
            log.info("removed %s, left by an earlier run (not asked for this time)", stale)
    if removed:
        outputs["removed"] = removed


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

        p = p / check_truth(load_scan(p, check_files=False, allow_incomplete=True))["mesh"]
    return read_mesh(p)
