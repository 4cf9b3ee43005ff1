"""Column/row Gray-code captures as OpenCV writes them, rendered on the virtual rig, with ground truth.

:func:`graycode_patterns` makes the projector frames of OpenCV's structured-light
module for a W_p x H_p projector (``cv::structured_light::GrayCodePattern::generate``
then ``getImagesForShadowMasks``): ``ceil(log2 W_p)`` column bits, most significant
first, each pattern followed by its inverse; then the ``ceil(log2 H_p)`` row bits
likewise; then white, then black. Bit k of column j is bit k of its binary-reflected
Gray code j ^ (j >> 1); a pattern is 255 where the bit is 1, 0 elsewhere.

:func:`render_graycode_captures` renders them with :class:`VirtualRig` (the same
ray tracer, defocus, gamma and noise as ``ringscan simulate``) and writes a folder
that ``ringscan import`` reads as it reads a real rig's captures::

    OUT/rig.json                        the rig rendered with (import with --rig OUT/rig.json)
    OUT/capture_0/graycode_00.png ...   the captures (layout opencv-graycode)
    OUT/truth.json                      what was rendered, and where the truth lies
    OUT/truth/object.ply                the scene's mesh (object, and wall when there is one), world mm
    OUT/truth/capture_0_depth.tiff      float32 camera-frame depth Z_c of each pixel's centre ray, NaN = no hit
    OUT/truth/capture_0_lit.png         255 where the centre ray meets a point the projector lights
    OUT/truth/capture_0_object.png      255 where the centre ray meets the object (not the wall or the plane)
    OUT/truth/capture_0_proj_u.tiff     float32 projector u_p of the point the centre ray meets (NaN = no hit)
    OUT/truth/capture_0_proj_v.tiff     float32 projector v_p likewise

A rig with a second camera (``rig.camera2``; :func:`~ringscan.pipeline.simulate.scan.add_camera2`
makes one) renders both cameras, as OpenCV's structured-light sample stores them::

    OUT/capture_0/pattern_cam1_im1.png ... pattern_cam2_imN.png   (from 1; same frame order)
    OUT/capture_0.yml                   the image list (cam1: [...], cam2: [...], relative paths)
    OUT/calibrationParameters.yml       the camera-camera calibration as the sample has it
                                        (cam1_intrinsics, cam1_distorsion, cam1_size, cam2_...,
                                        RT_cam1_2_cam2 (4x4), R, T; X_cam2 = R X_cam1 + T)
    OUT/procam.yml                      camera 1 and the projector (cam_int, cam_dist, proj_int,
                                        proj_dist, rotation, translation, img_shape), for comparison
    OUT/truth/capture_0_cam2_*.tiff/png camera 2's truth, as camera 1's

truth.json then records ``camera1_from_world`` (the 4x4 from the rendered world to camera
1's frame, the world of an imported stereo rig) and the files above.

Projector coordinates follow OpenCV's pixel convention (pixel i covers [i - 0.5,
i + 0.5]; the integer code of a pixel is its centre), which is the one the import
decodes to. The truth projector coordinates are the OpenCV projection
(``cv2.projectPoints``, lens distortion included) of the traced surface point:
code independent of the ray tracer's own projector model.

A pixel is on the object when its centre ray's point lies more than
``OBJECT_MIN_HEIGHT_MM`` in front of the wall (or of the reference plane z = 0
without a wall): an object touching the wall loses that thin rim to the wall.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import os
import time
from pathlib import Path

import numpy as np

from ringscan.pipeline.formats.atomic import atomic_write_json, read_json
from ringscan.pipeline.formats.errors import FormatError
from ringscan.pipeline.formats.images import read_image, write_image
from ringscan.pipeline.formats.patterns import gray_encode
from ringscan.pipeline.formats.rig import Rig, save_rig
from ringscan.pipeline.geometry import projector_pixels
from ringscan.pipeline.simulate.scan import prepare_scene
from ringscan.pipeline.simulate.scenes import SceneMesh
from ringscan.pipeline.simulate.truth import TRUTH_DIR, _write_depth, _write_mesh
from ringscan.pipeline.simulate.virtual_rig import RenderSettings, VirtualRig, _mix_seed

log = logging.getLogger(__name__)

LAYOUT = "opencv-graycode"
"""The capture layout written (``ringscan import --layout``)."""
CAPTURE = "capture_0"
"""The capture folder's name."""
TRUTH_FORMAT = "ringscan.graycode-truth/1"
OBJECT_MIN_HEIGHT_MM = 0.5
"""A traced point is on the object when it lies this far in front of the wall (or plane)."""
MAX_PROJECTOR_SIDE = 16384

STEREO_FILE = "calibrationParameters.yml"
"""The camera-camera calibration file of a two-camera rendering (OpenCV's sample's name)."""
PROCAM_FILE = "procam.yml"
"""Camera 1 and the projector, as ``ringscan import --rig`` reads an OpenCV procam file."""
IMAGE_LIST = f"{CAPTURE}.yml"
"""The image list of a two-camera rendering (``ringscan import OUT/capture_0.yml``)."""

__all__ = ["LAYOUT", "CAPTURE", "STEREO_FILE", "PROCAM_FILE", "IMAGE_LIST", "OBJECT_MIN_HEIGHT_MM",
           "graycode_bit_counts", "graycode_patterns", "graycode_frame_names", "graycode_outputs",
           "render_graycode_captures", "read_graycode_truth", "write_stereo_calibration",
           "write_procam_calibration"]


def graycode_bit_counts(projector: tuple[int, int]) -> tuple[int, int]:
    """(column bits, row bits) = (ceil(log2 W_p), ceil(log2 H_p)), as OpenCV counts them."""
    w, h = _check_projector(projector)
    return int(math.ceil(math.log2(w))), int(math.ceil(math.log2(h)))


def _check_projector(projector) -> tuple[int, int]:
    try:
        w, h = (int(x) for x in projector)
        ok = all(float(x) == int(x) for x in projector)
    except (TypeError, ValueError):
        ok = False
    if not ok or not (2 <= w <= MAX_PROJECTOR_SIDE and 2 <= h <= MAX_PROJECTOR_SIDE):
        raise ValueError(f"projector: expected (width, height), whole numbers in 2..{MAX_PROJECTOR_SIDE}, "
                         f"got {projector!r}")
    return w, h


def graycode_frame_names(projector: tuple[int, int], *, camera: int | None = None) -> list[str]:
    """The frame names in capture order (2 (column + row bits) patterns + white + black):
    ``graycode_00`` ..., or with ``camera`` OpenCV's sample's ``pattern_cam<camera>_im1`` ..."""
    cb, rb = graycode_bit_counts(projector)
    n = 2 * (cb + rb) + 2
    if camera is not None:
        return [f"pattern_cam{camera}_im{i + 1}" for i in range(n)]
    return [f"graycode_{i:02d}" for i in range(n)]


def graycode_patterns(projector: tuple[int, int]) -> list[np.ndarray]:
    """The projector frames in capture order, each (H_p, W_p) uint8 (see the module docstring)."""
    w, h = _check_projector(projector)
    cb, rb = graycode_bit_counts((w, h))
    out = []
    for n_bits, count, across in ((cb, w, True), (rb, h, False)):
        g = gray_encode(np.arange(count))
        for k in range(n_bits - 1, -1, -1):             # most significant first
            line = np.where((g >> k) & 1, 255, 0).astype(np.uint8)
            pat = np.broadcast_to(line[None, :] if across else line[:, None], (h, w))
            out += [np.ascontiguousarray(pat), np.ascontiguousarray(255 - pat)]
    out += [np.full((h, w), 255, np.uint8), np.zeros((h, w), np.uint8)]
    return out


def graycode_outputs(out_dir: str | os.PathLike, projector: tuple[int, int], *, cameras: int = 1) -> list[Path]:
    """Every file :func:`render_graycode_captures` writes (for overwrite checks)."""
    out = Path(out_dir)
    files = [out / "rig.json", out / "truth.json", out / TRUTH_DIR / "object.ply"]
    keys = ("depth.tiff", "lit.png", "object.png", "proj_u.tiff", "proj_v.tiff")
    if cameras == 1:
        files += [out / CAPTURE / f"{n}.png" for n in graycode_frame_names(projector)]
        files += [out / TRUTH_DIR / f"{CAPTURE}_{k}" for k in keys]
        return files
    files += [out / IMAGE_LIST, out / STEREO_FILE, out / PROCAM_FILE]
    for c in (1, 2):
        files += [out / CAPTURE / f"{n}.png" for n in graycode_frame_names(projector, camera=c)]
        files += [out / TRUTH_DIR / f"{CAPTURE}_{'cam2_' if c == 2 else ''}{k}" for k in keys]
    return files


def _write_storage(path: Path, write) -> None:
    """An OpenCV FileStorage file, written atomically (``write(fs)`` fills it)."""
    import cv2

    from ringscan.pipeline.formats.atomic import atomic_path

    with atomic_path(path) as tmp:
        fs = cv2.FileStorage(str(tmp), cv2.FILE_STORAGE_WRITE)
        try:
            write(fs)
        finally:
            fs.release()


def _write_seq(fs, name: str, values, flow: bool = False) -> None:
    import cv2

    fs.startWriteStruct(name, cv2.FileNode_SEQ | (cv2.FileNode_FLOW if flow else 0))
    for v in values:
        fs.write("", v)
    fs.endWriteStruct()


def _relative_pose(rig: Rig) -> tuple[np.ndarray, np.ndarray]:
    """(R, T) with X_cam2 = R X_cam1 + T."""
    c1, c2 = rig.camera, rig.camera2
    R = c2.R @ c1.R.T
    return R, c2.t - R @ c1.t


def write_stereo_calibration(path: str | os.PathLike, rig: Rig) -> None:
    """The rig's two cameras as OpenCV's structured-light sample's calibration file (see the module docstring)."""
    if rig.camera2 is None:
        raise ValueError("write_stereo_calibration: the rig has one camera")
    R, T = _relative_pose(rig)

    def write(fs):
        for c, cam in ((1, rig.camera), (2, rig.camera2)):
            fs.write(f"cam{c}_intrinsics", np.asarray(cam.K, np.float64))
            fs.write(f"cam{c}_distorsion", np.asarray(cam.dist, np.float64).reshape(1, -1))
            _write_seq(fs, f"cam{c}_size", [int(cam.width), int(cam.height)], flow=True)
        # in the order and shapes of the file of OpenCV's structured-light test data (RT 4x4)
        fs.write("RT_cam1_2_cam2", np.vstack([np.hstack([R, T.reshape(3, 1)]), [[0.0, 0.0, 0.0, 1.0]]]))
        fs.write("R", R)
        fs.write("T", T.reshape(3, 1))

    _write_storage(Path(path), write)


def write_procam_calibration(path: str | os.PathLike, rig: Rig) -> None:
    """Camera 1 and the rig's perspective projector as an OpenCV camera-projector file (cam_int, cam_dist,
    proj_int, proj_dist, rotation, translation with X_proj = R X_cam + T, img_shape [H, W])."""
    li = rig.light
    if not hasattr(li, "K"):
        raise ValueError("write_procam_calibration: the rig's light is not a perspective projector")
    c = rig.camera
    R = li.R @ c.R.T
    T = li.t - R @ c.t

    def write(fs):
        fs.write("img_shape", np.array([[c.height, c.width]], np.float64))
        fs.write("cam_int", np.asarray(c.K, np.float64))
        fs.write("cam_dist", np.asarray(c.dist, np.float64).reshape(1, -1))
        fs.write("proj_int", np.asarray(li.K, np.float64))
        fs.write("proj_dist", np.asarray(li.dist, np.float64).reshape(1, -1))
        fs.write("rotation", R)
        fs.write("translation", T.reshape(3, 1))

    _write_storage(Path(path), write)


def render_graycode_captures(
    out_dir: str | os.PathLike,
    *,
    rig: Rig,
    scene: SceneMesh | str | os.PathLike = "sphere",
    projector: tuple[int, int] | None = None,
    settings: RenderSettings = RenderSettings(),
    device: str | None = None,
    progress: bool = True,
    size_mm: float = 80.0,
    up: str = "auto",
    pose: str | None = None,
    place=None,
    wall_z: float | None = None,
) -> dict:
    """Render one capture of OpenCV's column/row Gray code on the virtual rig, with its ground truth.

    Args:
        out_dir: the folder to write (see the module docstring); created.
        rig: the rig; its light is the projector (its width and height are the
            pattern size).
        scene, size_mm, up, pose, place, wall_z: the scene
            (:func:`ringscan.pipeline.simulate.scan.prepare_scene`).
        projector: (W_p, H_p) expected of the rig's light (None: the light's own);
            a different size is an error.
        settings: rendering settings (noise, defocus, supersampling...).
        device: Warp device.
        progress: show progress (a bar on a terminal, log lines elsewhere).

    Returns:
        The ``truth.json`` document written.

    Raises:
        ValueError: a light without a size, a ``projector`` that is not the light's,
            or a bad scene; all before anything is written.

    Size: a public function: the output folder and its documented keyword-only options, one per user-facing
    setting (rig, scene, projector size, rendering, device, placement and pose).
    """
    from ringscan.pipeline.formats.progress import progress_bar

    proj = _checked_projector_size(rig, projector, settings)
    scene, placed = prepare_scene(scene, size_mm=size_mm, up=up, pose=pose, place=place, wall_z=wall_z)
    two = rig.camera2 is not None
    cams = [(1, rig)] + ([(2, dataclasses.replace(rig, camera=rig.camera2, camera2=rig.camera))] if two else [])
    renderers = {c: VirtualRig(crig, scene, settings=settings, device=device, projector_size=proj) for c, crig in cams}
    patterns = graycode_patterns(proj)

    out = Path(out_dir)
    mesh_rel = _write_rig_and_mesh(out, rig, scene)
    t0 = time.perf_counter()
    n_frames = len(patterns)
    bar = progress_bar(total=n_frames * len(cams), desc=f"simulate {LAYOUT} {scene.name}", unit="frame",
                       disable=not progress)
    try:
        captures, lists = _render_cameras(out, rig, renderers, patterns, proj, settings, bar,
                                          float(placed.get("wall_z", 0.0)))
    finally:
        bar.close()
    doc = {"format": TRUTH_FORMAT, "layout": LAYOUT, "projector": list(proj),
           "camera": [rig.camera.width, rig.camera.height], "rig": "rig.json", "mesh": mesh_rel,
           "scene": scene.name, "size_mm": float(size_mm), "reference_plane_z": 0.0, **placed,
           "object_min_height_mm": OBJECT_MIN_HEIGHT_MM, "settings": settings.to_dict(),
           "captures": {CAPTURE: captures}}
    if two:
        _write_stereo_files(out, rig, lists, doc)
    atomic_write_json(out / "truth.json", doc)
    log.info("rendered %d %s frames x %d camera(s) of %s in %.1f s -> %s", n_frames, LAYOUT, len(cams), scene.name,
             time.perf_counter() - t0, out)
    return doc


def _checked_projector_size(rig, projector, settings) -> tuple[int, int]:
    """The rig's projector size (W_p, H_p), after checking the rig, ``projector`` and ``settings``."""
    if not isinstance(rig, Rig):
        raise ValueError(f"rig: expected a Rig, got {type(rig).__name__}")
    lw, lh = getattr(rig.light, "width", 0), getattr(rig.light, "height", 0)
    if not (lw and lh):
        raise ValueError("rig: its light does not state its size (width, height): no projector to show the code")
    if projector is not None and tuple(_check_projector(projector)) != (lw, lh):
        pw, ph = _check_projector(projector)
        raise ValueError(f"projector {pw}x{ph} does not match the rig's {lw}x{lh} projector")
    if not isinstance(settings, RenderSettings):
        raise ValueError(f"settings: expected RenderSettings, got {type(settings).__name__}")
    proj = (int(lw), int(lh))
    if getattr(rig.light, "model", "") == "uncalibrated":
        raise ValueError("rig: the virtual rig renders with a calibrated projector (its light is 'uncalibrated')")
    return proj


def _write_rig_and_mesh(out: Path, rig: Rig, scene: SceneMesh) -> str:
    """Create the capture and truth folders, write rig.json and the scene's mesh; the mesh's relative path."""
    (out / CAPTURE).mkdir(parents=True, exist_ok=True)
    (out / TRUTH_DIR).mkdir(parents=True, exist_ok=True)
    save_rig(out / "rig.json", rig)
    mesh_rel = f"{TRUTH_DIR}/object.ply"
    _write_mesh(out / mesh_rel, scene.vertices, scene.faces)
    return mesh_rel


def _render_cameras(out: Path, rig: Rig, renderers: dict, patterns, proj: tuple[int, int],
                    settings: RenderSettings, bar, floor: float) -> tuple[dict, dict]:
    """Render every camera's frames and truth (each renderer freed once done); the captures entry and image lists."""
    two = rig.camera2 is not None
    captures: dict = {"frames": len(patterns)}
    lists = {}
    for c in list(renderers):
        vr = renderers.pop(c)
        names = graycode_frame_names(proj, camera=c if two else None)
        for fi, (n, pat) in enumerate(zip(names, patterns)):
            seed = _mix_seed(settings.seed, 0, fi) if c == 1 else _mix_seed(settings.seed, 0, fi, c)
            write_image(out / CAPTURE / f"{n}.png", vr.render(pat, seed=seed))
            bar.update(1)
        lists[c] = [f"{CAPTURE}/{n}.png" for n in names]
        rel = _write_camera_truth(out, rig, vr.truth(), c, floor)
        if c == 1:
            captures.update(rel)
        else:
            captures["camera2"] = rel
        del vr
    return captures, lists


def _write_camera_truth(out: Path, rig: Rig, tr: dict, c: int, floor: float) -> dict:
    """Write camera ``c``'s truth images (depth, lit, object, projector u/v); their relative paths."""
    pts = tr["points"].astype(np.float64)
    hit = np.all(np.isfinite(pts), axis=-1)
    obj = hit & (np.where(hit, pts[..., 2], -np.inf) > floor + OBJECT_MIN_HEIGHT_MM)
    uvp = np.full(hit.shape + (2,), np.nan, np.float32)
    uvp[hit] = projector_pixels(rig, pts[hit]).astype(np.float32)
    pre = f"{TRUTH_DIR}/{CAPTURE}_{'cam2_' if c == 2 else ''}"
    rel = {k: f"{pre}{k}.{ext}" for k, ext in
           (("depth", "tiff"), ("lit", "png"), ("object", "png"), ("proj_u", "tiff"), ("proj_v", "tiff"))}
    _write_depth(out / rel["depth"], tr["depth"])
    _write_depth(out / rel["proj_u"], uvp[..., 0])
    _write_depth(out / rel["proj_v"], uvp[..., 1])
    write_image(out / rel["lit"], np.where(tr["lit"], 255, 0).astype(np.uint8))
    write_image(out / rel["object"], np.where(obj, 255, 0).astype(np.uint8))
    return rel


def _write_stereo_files(out: Path, rig: Rig, lists: dict, doc: dict) -> None:
    """Write a two-camera render's image list and calibration files, and record them in ``doc``."""
    def write_list(fs):
        for c in (1, 2):
            _write_seq(fs, f"cam{c}", lists[c])

    _write_storage(out / IMAGE_LIST, write_list)
    write_stereo_calibration(out / STEREO_FILE, rig)
    T1 = np.eye(4)
    T1[:3, :3], T1[:3, 3] = rig.camera.R, rig.camera.t
    doc.update({"camera2": [rig.camera2.width, rig.camera2.height], "image_list": IMAGE_LIST,
                "stereo_calibration": STEREO_FILE, "camera1_from_world": T1.tolist()})
    if hasattr(rig.light, "K"):  # a perspective projector (a parallel light has no OpenCV procam file)
        write_procam_calibration(out / PROCAM_FILE, rig)
        doc["procam_calibration"] = PROCAM_FILE


def read_graycode_truth(folder: str | os.PathLike, capture: str = CAPTURE, *, camera: int = 1) -> dict:
    """The truth of :func:`render_graycode_captures` for one capture, seen by camera 1 or 2.

    Returns:
        dict: ``doc`` (truth.json), ``depth`` (H, W) float32, ``lit`` and ``object``
        (H, W) bool, ``proj`` (H, W, 2) float32 projector (u_p, v_p), ``mesh`` (the
        mesh file's path).

    Raises:
        FormatError: naming the file that is missing or not what it should be.
    """
    import cv2

    folder = Path(folder)
    doc = read_json(folder / "truth.json")
    if not isinstance(doc, dict) or doc.get("format") != TRUTH_FORMAT:
        raise FormatError(folder / "truth.json", f"not a {TRUTH_FORMAT} file (format {doc.get('format')!r})"
                          if isinstance(doc, dict) else "not a JSON object")
    caps = doc.get("captures", {})
    if capture not in caps:
        raise FormatError(folder / "truth.json", f"no capture {capture!r} (have {', '.join(caps) or 'none'})")
    c = caps[capture]
    if camera == 2:
        if not isinstance(c.get("camera2"), dict):
            raise FormatError(folder / "truth.json", f"captures.{capture}: no camera2 (a one-camera rendering)")
        c = c["camera2"]
    elif camera != 1:
        raise ValueError(f"camera must be 1 or 2, got {camera!r}")

    def path(key):
        rel = c.get(key)
        if not isinstance(rel, str) or ".." in Path(rel).parts or os.path.isabs(rel):
            raise FormatError(folder / "truth.json", f"captures.{capture}.{key}: bad path {rel!r}")
        p = folder / rel
        if not p.is_file():
            raise FormatError(p, "truth file not found (listed in truth.json)")
        return p

    def tiff(key):
        p = path(key)
        a = cv2.imread(str(p), cv2.IMREAD_UNCHANGED)
        if a is None or a.dtype != np.float32 or a.ndim != 2:
            raise FormatError(p, "not a single-channel float32 TIFF")
        return a

    out = {"doc": doc, "depth": tiff("depth"), "lit": read_image(path("lit")) > 0,
           "object": read_image(path("object")) > 0, "proj": np.stack([tiff("proj_u"), tiff("proj_v")], -1),
           "mesh": folder / doc.get("mesh", f"{TRUTH_DIR}/object.ply")}
    shapes = {k: out[k].shape[:2] for k in ("depth", "lit", "object", "proj")}
    if len(set(shapes.values())) != 1:
        raise FormatError(folder / "truth.json", f"truth images of different sizes: {shapes}")
    return out
