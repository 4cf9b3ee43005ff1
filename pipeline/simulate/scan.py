"""``ringscan simulate``: render a whole scan folder with the virtual rig, with its ground truth."""

from __future__ import annotations

import dataclasses
import logging
import os
import time
from pathlib import Path

import numpy as np

from ringscan.pipeline.codecs.render import render_frame
from ringscan.pipeline.formats.images import write_image
from ringscan.pipeline.formats.patterns import PatternSpec, frame_names
from ringscan.pipeline.formats.rig import Rig, default_rig, has_calibrated_light, rig_to_dict, turntable_transform
from ringscan.pipeline.formats.frame_store import STORE_NAME, create_store, write_frame
from ringscan.pipeline.formats.scan import Scan, View, load_scan, packed_view, save_scan
from ringscan.pipeline.simulate.scenes import SceneMesh, add_wall, make_scene, place_scene, pose_scene
from ringscan.pipeline.simulate.truth import TRUTH_DIR, _write_depth, _write_mesh
from ringscan.pipeline.simulate.virtual_rig import RenderSettings, VirtualRig, _mix_seed, view_angles

log = logging.getLogger(__name__)

CAMERA2_DIR = "cam2"
"""Camera 2's frames of a view go to ``<view>/cam2/`` (a two-camera rig)."""

__all__ = ["simulate_scan", "prepare_scene", "add_camera2"]


def add_camera2(rig: Rig) -> Rig:
    """The rig with a second camera: camera 1 turned by 180 degrees about the light axis (the world
    z axis, docs/design.md §2), so that the two stand symmetric about it, looking at the same point
    from opposite sides (the default rig: 482 mm apart, 70 degrees between their axes).

    Raises:
        ValueError: the rig has a second camera already.
    """
    if rig.camera2 is not None:
        raise ValueError("add_camera2: the rig has a second camera already")
    c = rig.camera
    flip = np.diag([-1.0, -1.0, 1.0])  # 180 degrees about world z
    cam2 = dataclasses.replace(c, R=c.R @ flip, t=c.t.copy())
    return dataclasses.replace(rig, camera2=cam2)


def prepare_scene(scene: SceneMesh | str | os.PathLike, *, size_mm: float = 80.0, up: str = "auto",
                  pose: str | None = None, place=None, wall_z: float | None = None) -> tuple[SceneMesh, dict]:
    """The scene as the virtual rig renders it: made (or loaded), posed, placed, with its wall.

    Args:
        scene: a :class:`SceneMesh`, a procedural scene name or a mesh file path.
        size_mm, up: for :func:`make_scene` when ``scene`` is a name or path.
        pose: see :func:`pose_scene` (None: as made).
        place: (x, y, z) world mm for the centre of the object's bounding box
            (:func:`place_scene`); None: standing on z = 0, centred on the light axis.
        wall_z: add a wall, the plane z = ``wall_z`` (:func:`add_wall`); None: none
            (the reference plane z = 0 is always there).

    Returns:
        (scene, truth): ``truth`` the scan.json ``truth`` entries that record it:
        ``pose`` ({"name", "transform"}: the 4x4 from the upright scene to the posed
        and placed one) when posed or placed, ``wall_z`` when a wall was added.
    """
    if not isinstance(scene, SceneMesh):
        scene = make_scene(scene, size_mm=size_mm, up=up)
    info: dict = {}
    T = np.eye(4)
    if pose is not None:
        scene, T = pose_scene(scene, pose)
    if place is not None:
        scene, Tp = place_scene(scene, place)
        T = Tp @ T
    if pose is not None or place is not None:
        info["pose"] = {"name": str(pose or "upright"), "transform": T.tolist()}
        if place is not None:
            info["pose"]["place"] = [float(c) for c in place]
    if wall_z is not None:
        scene = add_wall(scene, float(wall_z))
        info["wall_z"] = float(wall_z)
    return scene, info


def simulate_scan(
    out_dir: str | os.PathLike,
    *,
    scene: SceneMesh | str | os.PathLike = "sphere",
    rig: Rig | None = None,
    patterns: PatternSpec,
    turntable_deg=(0.0,),
    views: int | None = None,
    settings: RenderSettings = RenderSettings(),
    device: str | None = None,
    progress: bool = True,
    size_mm: float = 80.0,
    up: str = "auto",
    image_format: str = "png",
    pose: str | None = None,
    place=None,
    wall_z: float | None = None,
    renderer: str = "warp",
    mitsuba=None,
) -> Scan:
    """Render a whole scan with the virtual rig and write it with its ground truth.

    Args:
        out_dir: the scan folder (created; files of an earlier scan there are replaced).
        scene: a :class:`SceneMesh`, a procedural scene name or a mesh file path.
        rig: the rig (default: :func:`default_rig`).
        patterns: the pattern set to project.
        turntable_deg: the views' turntable angles (degrees).
        views: if given, ``views`` equal steps k * 360 / views instead of ``turntable_deg``.
        settings: rendering settings.
        device: Warp device.
        progress: show a progress bar.
        size_mm, up: passed to :func:`make_scene` when ``scene`` is a name or path.
        image_format: ``png`` or ``tiff`` for the frames, or ``packed``: one frame store per view
            (``<view>/frames.zarr``, frames appended as they are rendered).
            A rig with ``camera2`` (:func:`add_camera2`) renders camera 2 too: its frames in
            ``<view>/cam2/``, the view's ``camera2`` in scan.json, its truth as
            ``truth/<view>_cam2_depth.tiff`` and ``_cam2_lit.png`` (``truth.views.<view>.camera2``).
        pose: turn the placed scene into this resting pose first (see
            :func:`ringscan.pipeline.simulate.scenes.pose_scene`: ``upright``, ``upside-down``,
            ``side-x``, ``side-y`` or ``AXIS:DEG[,AXIS:DEG...]``); None keeps it as it is.
            The truth mesh is the posed scene, and scan.json ``truth.pose`` records
            the transform from the upright scene.
        place, wall_z: see :func:`prepare_scene` (a bust in front of a wall: the
            object floats at ``place``, the wall, part of the truth mesh, behind it).
        renderer: ``warp`` (ringscan's own ray tracer, :class:`VirtualRig`) or ``mitsuba``
            (Mitsuba 3, an independent renderer: :class:`~ringscan.pipeline.simulate.mitsuba_render.MitsubaRig`;
            ``device`` does not apply); the files written are the same, and scan.json
            ``truth.renderer`` records Mitsuba's version, variant and settings.
        mitsuba: :class:`~ringscan.pipeline.simulate.mitsuba_render.MitsubaSettings` for
            ``renderer="mitsuba"`` (None: the defaults).

    Returns:
        The written scan (as :func:`load_scan` reads it back).

    Size: a public function (ringscan simulate's): the output folder and its documented keyword-only options,
    one per user-facing setting (scene, rig, patterns, views, rendering, device, placement and pose, image
    format, renderer).
    """
    _check_simulate_options(patterns, renderer, mitsuba, image_format)
    rig = default_rig() if rig is None else rig
    angles = _checked_angles(rig, views, turntable_deg)
    scene, placed = prepare_scene(scene, size_mm=size_mm, up=up, pose=pose, place=place, wall_z=wall_z)
    renderers = _renderers(rig, scene, patterns, renderer, settings, device, mitsuba)
    folder = Path(out_dir)
    scan, truth = _start_scan(folder, rig, patterns, scene, settings, renderer, renderers[0], placed)
    names = frame_names(patterns)
    out = _FrameWriter(folder=folder, names=names, frames={n: render_frame(patterns, n) for n in names},
                       settings=settings, image_format=image_format)
    t0 = time.perf_counter()
    by = " (Mitsuba)" if renderer == "mitsuba" else ""
    _render_views(out, scan, truth, angles, renderers, f"simulate {scene.name}{by}", progress)
    log.info("simulated %d view(s) x %d frame(s) of %s in %.1f s -> %s", len(angles), len(names), scene.name,
             time.perf_counter() - t0, folder)
    return load_scan(folder)


def _check_simulate_options(patterns, renderer: str, mitsuba, image_format: str) -> None:
    """Raise ValueError for a pattern set, renderer, Mitsuba settings or image format simulate_scan does not take."""
    if not isinstance(patterns, PatternSpec):
        raise ValueError(f"patterns: expected a PatternSpec, got {type(patterns).__name__}")
    if renderer not in ("warp", "mitsuba"):
        raise ValueError(f"renderer: expected 'warp' or 'mitsuba', got {renderer!r}")
    if mitsuba is not None and renderer != "mitsuba":
        raise ValueError("mitsuba: Mitsuba's settings apply to renderer='mitsuba' only")
    if image_format not in ("png", "tiff", "packed"):
        raise ValueError(f"image_format: expected 'png', 'tiff' or 'packed', got {image_format!r}")


def _checked_angles(rig: Rig, views: int | None, turntable_deg) -> tuple[float, ...]:
    """The views' turntable angles, checked against the rig's turntable, and the rig's light checked calibrated."""
    angles = view_angles(views) if views is not None else tuple(float(a) for a in turntable_deg)
    if not angles:
        raise ValueError("turntable_deg: no views")
    for a in angles:
        turntable_transform(rig.turntable, a)
    if not has_calibrated_light(rig):
        raise ValueError("rig: the virtual rig renders with a calibrated projector (its light is 'uncalibrated')")
    return angles


def _make_renderer(r: Rig, scene: SceneMesh, patterns: PatternSpec, renderer: str, settings: RenderSettings,
                   device: str | None, mitsuba):
    """The renderer (``warp``: :class:`VirtualRig`, ``mitsuba``: ``MitsubaRig``) of camera 1 of ``r``."""
    size = (patterns.width, patterns.height)
    if renderer == "mitsuba":
        from ringscan.pipeline.simulate.mitsuba_render import MitsubaRig, MitsubaSettings

        return MitsubaRig(r, scene, settings=settings, mitsuba=mitsuba or MitsubaSettings(), projector_size=size)
    return VirtualRig(r, scene, settings=settings, device=device, projector_size=size)


def _renderers(rig: Rig, scene: SceneMesh, patterns: PatternSpec, renderer: str, settings: RenderSettings,
               device: str | None, mitsuba) -> tuple:
    """(camera 1's renderer, camera 2's or None): camera 2 sees the same scene under the same frames."""
    vr = _make_renderer(rig, scene, patterns, renderer, settings, device, mitsuba)
    vr2 = None
    if rig.camera2 is not None:
        vr2 = _make_renderer(dataclasses.replace(rig, camera=rig.camera2, camera2=rig.camera), scene, patterns,
                             renderer, settings, device, mitsuba)
    return vr, vr2


def _start_scan(folder: Path, rig: Rig, patterns: PatternSpec, scene: SceneMesh, settings: RenderSettings,
                renderer: str, vr, placed: dict) -> tuple[Scan, dict]:
    """The scan folder with its truth mesh and a scan.json of no views yet: (the scan, its truth entries)."""
    folder.mkdir(parents=True, exist_ok=True)
    mesh_rel = f"{TRUTH_DIR}/object.ply"
    _write_mesh(folder / mesh_rel, scene.vertices, scene.faces)    # empty for the plane scene
    # the light rendered with: evaluate's coverage reads it where the scan's rig is later given an uncalibrated one
    truth = {"mesh": mesh_rel, "reference_plane_z": 0.0, "scene": scene.name, "views": {},
             "settings": settings.to_dict(), "light": rig_to_dict(rig)["light"]}
    if renderer == "mitsuba":
        truth["renderer"] = vr.describe()
    truth.update(placed)
    scan = Scan(folder=folder, rig=rig, patterns=patterns, views=(), extra={"truth": {**truth, "views": {}}})
    save_scan(scan)
    return scan, truth


@dataclasses.dataclass(frozen=True)
class _FrameWriter:
    """Where and how :func:`simulate_scan` writes the frames it renders."""

    folder: Path
    names: list
    frames: dict
    settings: RenderSettings
    image_format: str


def _render_views(out: _FrameWriter, scan: Scan, truth: dict, angles, renderers: tuple, desc: str,
                  progress: bool) -> None:
    """Every view rendered and written, scan.json saved after each (with the truth so far)."""
    from ringscan.pipeline.formats.progress import progress_bar

    vr, vr2 = renderers
    done: list[View] = []
    n_cams = 2 if vr2 is not None else 1
    bar = progress_bar(total=len(angles) * len(out.names) * n_cams, desc=desc, unit="frame", disable=not progress)
    try:
        for vi, deg in enumerate(angles):
            vname = f"view_{vi:03d}"
            cams = [(1, vr, vname)] + ([(2, vr2, f"{vname}/{CAMERA2_DIR}")] if vr2 is not None else [])
            written = {c: _render_camera(out, bar, rend, c, vi, deg, vname, sub) for c, rend, sub in cams}
            done.append(_add_view_truth(truth, vname, written))
            snapshot = {**truth, "views": dict(truth["views"])}
            scan = dataclasses.replace(scan, views=tuple(done), extra={"truth": snapshot})
            save_scan(scan)
    finally:
        bar.close()


def _render_camera(out: _FrameWriter, bar, rend, c: int, vi: int, deg: float, vname: str,
                   sub: str) -> tuple[dict, View]:
    """One camera's frames and truth of one view written: (its truth entry, its view)."""
    folder, names, frames, settings, image_format = out.folder, out.names, out.frames, out.settings, out.image_format
    rend.set_turntable(deg)
    cam = rend.rig.camera
    rel, store = {}, None
    if image_format == "packed":
        store = create_store(folder / sub / STORE_NAME, names, height=cam.height, width=cam.width,
                             dtype=np.uint16 if settings.bit_depth == 16 else np.uint8)
    for fi, n in enumerate(names):
        seed = _mix_seed(settings.seed, vi, fi) if c == 1 else _mix_seed(settings.seed, vi, fi, c)
        img = rend.render(frames[n], seed=seed)
        if store is not None:
            write_frame(store, n, img)
        else:
            rel[n] = f"{sub}/{n}.{image_format}"
            write_image(folder / rel[n], img)
        bar.update(1)
    tr = rend.truth()
    pre = f"{TRUTH_DIR}/{vname}_{'cam2_' if c == 2 else ''}"
    depth_rel, lit_rel = f"{pre}depth.tiff", f"{pre}lit.png"
    _write_depth(folder / depth_rel, tr["depth"])
    write_image(folder / lit_rel, np.where(tr["lit"], 255, 0).astype(np.uint8))
    view = View(name=vname, turntable_deg=float(deg), frames=rel)
    return ({"depth": depth_rel, "lit": lit_rel},
            packed_view(view, f"{sub}/{STORE_NAME}", names) if store is not None else view)


def _add_view_truth(truth: dict, vname: str, written: dict) -> View:
    """The view of its cameras' written frames (camera 2's as its ``camera2``), its truth entries put in ``truth``."""
    truth["views"][vname] = dict(written[1][0])
    view = written[1][1]
    if 2 in written:
        truth["views"][vname]["camera2"] = written[2][0]
        view = dataclasses.replace(view, camera2=written[2][1])
    return view
