"""Offscreen renders of point clouds and meshes (colour maps, heat maps and ring
overlays are in :mod:`.colour`).

- :func:`render_geometries` renders Open3D point clouds and meshes to an RGB image
  with Open3D's ``OffscreenRenderer`` (Filament; on a machine without a GPU it runs
  on Mesa's llvmpipe Vulkan driver: Debian/Ubuntu packages ``libvulkan1`` and
  ``mesa-vulkan-drivers``). Filament aborts the whole process when it cannot start,
  so renderer="auto" first probes it once in a child process; when the probe fails
  it falls back to a software point-splat renderer written in NumPy (lower quality,
  same camera) and logs a warning. ``RINGSCAN_RENDERER=open3d|software`` forces one.
- :func:`render_to_png` writes such a render to a PNG; :func:`read_geometry` reads a
  cloud or mesh file for it.

Both renderers use one pinhole camera (:func:`view_camera`, OpenCV convention), so
a point ``X`` of a geometry lands at pixel ``K (R X + t)`` of the render.
"""

from __future__ import annotations

import functools
import logging
import math
import os
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ringscan.pipeline.formats.errors import FormatError
from ringscan.pipeline.formats.images import write_image
from ringscan.pipeline.formats.meshes import MESH_FORMATS, drop_non_finite, read_cloud
from ringscan.pipeline.formats.ply import check_ply
from ringscan.pipeline.preview.colour import colorbar, colorbar_labels

log = logging.getLogger(__name__)

__all__ = ["RENDERER_ENV", "ViewSettings", "RenderResult", "view_camera", "offscreen_available", "render_geometries", "render_to_png", "read_geometry"]

RENDERER_ENV = "RINGSCAN_RENDERER"
_SUN_LUX = 120000.0
_SKY_INTENSITY = 45000.0


# ----------------------------------------------------------------------------- settings


@dataclass(frozen=True)
class ViewSettings:
    """How a 3D render is framed and drawn."""

    width: int = 960
    """Image width in pixels."""
    height: int = 720
    """Image height in pixels."""
    azimuth_deg: float = -60.0
    """Viewing direction about the object's z axis (0: from +x, -90: from -y)."""
    elevation_deg: float = 30.0
    """Viewing direction above the x-y plane (the turntable plane)."""
    fov_deg: float = 30.0
    """Vertical field of view."""
    margin: float = 1.08
    """The bounding sphere fills 1/margin of the narrower field of view."""
    background: tuple = (1.0, 1.0, 1.0)
    """Background colour (RGB in 0..1)."""
    color: tuple = (0.70, 0.72, 0.78)
    """Colour of geometries that carry no colours of their own."""
    point_size: float = 3.0
    """Point size in pixels for point clouds."""
    renderer: str = "auto"
    """"auto" (Open3D when it can start, else software), "open3d" or "software"."""
    timeout_s: float = 120.0
    """An Open3D render still running after this long is stopped (then "auto" falls
    back to the software renderer). On Mesa's llvmpipe a few meshes (Open3D's own
    UV spheres at some resolutions) take tens of seconds."""


@dataclass
class RenderResult:
    """A render and the camera that made it."""

    image: np.ndarray
    """(H, W, 3) uint8 RGB."""
    K: np.ndarray
    """3x3 intrinsics."""
    E: np.ndarray
    """4x4 extrinsics (object -> camera, OpenCV: x right, y down, z forward)."""
    renderer: str
    """"open3d" or "software"."""
    png_size: tuple[int, int] | None = None
    """(width, height) of the PNG :func:`render_to_png` wrote, colour bar included."""
    scale_bar_mm: float | None = None
    """The length of the scale bar :func:`render_to_png` drew, in its ``length_unit`` (None: none drawn)."""
    scale_bar_label: str | None = None
    """The scale bar's label as drawn (``"20 mm"``, ``"20 board units"``)."""
    legend: list | None = None
    """The colour bar's labels as drawn: its round ticks, or one name a category (None: no bar)."""
    empty_label: str | None = None
    """The key of the hatched pixels where nothing was drawn, as drawn (None: left plain)."""


# ----------------------------------------------------------------------------- camera


def _bounds(geoms) -> tuple[np.ndarray, np.ndarray]:
    lo = np.full(3, np.inf)
    hi = np.full(3, -np.inf)
    for g in geoms:
        pts = np.asarray(g.vertices if hasattr(g, "triangles") else g.points)
        pts = pts[np.all(np.isfinite(pts), axis=1)]
        if len(pts):
            lo = np.minimum(lo, pts.min(axis=0))
            hi = np.maximum(hi, pts.max(axis=0))
    if not np.all(np.isfinite(lo)):
        raise ValueError("nothing to render: every geometry is empty (or has no finite point)")
    return lo, hi


def view_camera(geoms, *, settings: ViewSettings = ViewSettings()) -> tuple[np.ndarray, np.ndarray]:
    """The camera (K, E) that frames ``geoms`` (or a (lo, hi) bounds pair) from the
    settings' azimuth and elevation, object z up in the image."""
    s = settings
    if isinstance(geoms, tuple) and len(geoms) == 2 and np.shape(geoms[0]) == (3,):
        lo, hi = np.asarray(geoms[0], float), np.asarray(geoms[1], float)
    else:
        lo, hi = _bounds(geoms)
    ctr = 0.5 * (lo + hi)
    radius = max(0.5 * float(np.linalg.norm(hi - lo)), 1e-6)
    fy = (s.height / 2.0) / math.tan(math.radians(s.fov_deg) / 2.0)
    half = min(math.atan((s.width / 2.0) / fy), math.radians(s.fov_deg) / 2.0)
    dist = radius * s.margin / math.sin(half)
    az, el = math.radians(s.azimuth_deg), math.radians(s.elevation_deg)
    d = np.array([math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el)])
    eye = ctr + dist * d
    fwd = -d
    up = np.array([0.0, 0.0, 1.0]) if abs(d[2]) < 0.999 else np.array([0.0, 1.0, 0.0])
    x = np.cross(fwd, up)
    x /= np.linalg.norm(x)
    y = np.cross(fwd, x)
    R = np.stack([x, y, fwd])
    E = np.eye(4)
    E[:3, :3], E[:3, 3] = R, -R @ eye
    K = np.array([[fy, 0.0, (s.width - 1) / 2.0], [0.0, fy, (s.height - 1) / 2.0], [0.0, 0.0, 1.0]])
    return K, E


# ----------------------------------------------------------------------------- renderers


def _render_open3d_here(geoms, K, E, s: ViewSettings) -> np.ndarray:
    """Render with Open3D's OffscreenRenderer in this process (the child's side)."""
    import open3d as o3d

    rendering = o3d.visualization.rendering
    r = rendering.OffscreenRenderer(s.width, s.height)
    r.scene.view.set_post_processing(False)  # exact background, no tone mapping
    r.scene.set_background([*map(float, s.background), 1.0])
    r.scene.scene.set_sun_light(E[2, :3] + np.array([0.0, 0.0, -0.6]), [1.0, 1.0, 1.0], _SUN_LUX)
    r.scene.scene.enable_sun_light(True)
    r.scene.scene.set_indirect_light_intensity(_SKY_INTENSITY)
    for i, g in enumerate(geoms):
        mat = rendering.MaterialRecord()
        is_mesh = hasattr(g, "triangles")
        has_col = g.has_vertex_colors() if is_mesh else g.has_colors()
        has_nrm = g.has_vertex_normals() if is_mesh else g.has_normals()
        # Coloured geometries (colour maps) are drawn unlit, so that the colours match
        # their colour bar; plain ones are shaded.
        mat.shader = "defaultLit" if has_nrm and not has_col else "defaultUnlit"
        mat.base_color = [1.0, 1.0, 1.0, 1.0] if has_col else [*map(float, s.color), 1.0]
        mat.point_size = float(s.point_size)
        r.scene.add_geometry(f"g{i}", g, mat)
    r.setup_camera(K, E, s.width, s.height)
    return np.asarray(r.render_to_image()).copy()


def _child_main(job_dir: str) -> None:
    """Entry point of the render child process: job.json + geometry files -> image.npy."""
    import json

    import open3d as o3d

    job = json.loads((Path(job_dir) / "job.json").read_text())
    geoms = []
    for g in job["geoms"]:
        if g["kind"] == "mesh":
            geoms.append(o3d.io.read_triangle_mesh(g["path"]))
        else:
            geoms.append(o3d.io.read_point_cloud(g["path"]))
    s = ViewSettings(**{k: tuple(v) if isinstance(v, list) else v for k, v in job["settings"].items()})
    img = _render_open3d_here(geoms, np.asarray(job["K"]), np.asarray(job["E"]), s)
    np.save(Path(job_dir) / "image.npy", img)


def _render_open3d(geoms, K, E, s: ViewSettings) -> np.ndarray:
    """Render with Open3D in a child process.

    Filament aborts the process when it cannot start (no Vulkan driver) and, in
    Open3D 0.20, hangs when a process makes its fourth OffscreenRenderer; a child
    per render keeps the caller safe from both. Raises RuntimeError on failure.
    """
    import dataclasses
    import json
    import tempfile

    import open3d as o3d

    with tempfile.TemporaryDirectory(prefix="ringscan-render-") as tmp:
        items = []
        for i, g in enumerate(geoms):
            path = os.path.join(tmp, f"g{i}.ply")
            if hasattr(g, "triangles"):
                ok = o3d.io.write_triangle_mesh(path, g, write_ascii=False)
                items.append({"kind": "mesh", "path": path})
            else:
                ok = o3d.io.write_point_cloud(path, g, write_ascii=False)
                items.append({"kind": "cloud", "path": path})
            if not ok:
                raise RuntimeError(f"could not write geometry {i} for the renderer")
        job = {"settings": dataclasses.asdict(s), "K": np.asarray(K).tolist(), "E": np.asarray(E).tolist(),
               "geoms": items}
        Path(tmp, "job.json").write_text(json.dumps(job))
        code = f"from ringscan.pipeline.preview.render import _child_main; _child_main({tmp!r})"
        try:
            res = subprocess.run([sys.executable, "-c", code], capture_output=True, timeout=s.timeout_s)
        except subprocess.TimeoutExpired:
            raise RuntimeError(f"the Open3D renderer did not finish within {s.timeout_s:g} s") from None
        out = Path(tmp, "image.npy")
        if res.returncode != 0 or not out.is_file():
            tail = (res.stderr or b"").decode(errors="replace").strip().splitlines()[-3:]
            raise RuntimeError("the Open3D renderer could not start or failed (exit code "
                               f"{res.returncode}): {' | '.join(tail) or 'no message'}")
        return np.load(out)


@functools.lru_cache(maxsize=1)
def offscreen_available() -> bool:
    """True when Open3D's OffscreenRenderer works on this machine (one tiny render
    in a child process; the answer is cached)."""
    import open3d as o3d

    pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.zeros((1, 3))))
    # 16x16 px take 3-10 s on a loaded 2-core machine (the child's imports); Open3D's
    # offscreen start now and then hangs instead (a suite run waited 60 s here once): past
    # 25 s the software renderer draws the previews
    s = ViewSettings(width=16, height=16, timeout_s=25.0)
    try:
        _render_open3d([pc], *view_camera(([-1.0, -1, -1], [1.0, 1, 1]), settings=s), s)
    except RuntimeError as e:
        log.info("Open3D offscreen rendering is not available: %s", e)
        return False
    return True


def _choose_renderer(name: str) -> str:
    name = os.environ.get(RENDERER_ENV, name) if name == "auto" else name
    if name not in ("auto", "open3d", "software"):
        raise ValueError(f"renderer must be 'auto', 'open3d' or 'software', got {name!r}")
    return name


def _software_points(g, n_target: int):
    """(points, normals or None, colours or None) to splat for one geometry."""
    if hasattr(g, "triangles"):
        if len(g.triangles) == 0:
            return np.asarray(g.vertices), None, None
        import open3d as o3d

        gm = o3d.geometry.TriangleMesh(g)
        if not gm.has_triangle_normals():
            gm.compute_triangle_normals()
        pc = gm.sample_points_uniformly(n_target, use_triangle_normal=True)
        return np.asarray(pc.points), np.asarray(pc.normals), (np.asarray(pc.colors) if pc.has_colors() else None)
    return (np.asarray(g.points), np.asarray(g.normals) if g.has_normals() else None,
            np.asarray(g.colors) if g.has_colors() else None)


def _render_software(geoms, K, E, s: ViewSettings) -> np.ndarray:
    """Z-buffered square splats with headlight Lambert shading (NumPy)."""
    H, W = s.height, s.width
    img = np.empty((H, W, 3), np.float64)
    img[:] = np.asarray(s.background, float)
    zbuf = np.full(H * W, np.inf)
    R, t = E[:3, :3], E[:3, 3]
    for g in geoms:
        pts, nrm, col = _software_points(g, max(4 * W * H, 200_000))
        if len(pts) == 0:
            continue
        pc = pts @ R.T + t
        ok = pc[:, 2] > 1e-6
        pc = pc[ok]
        u = K[0, 0] * pc[:, 0] / pc[:, 2] + K[0, 2]
        v = K[1, 1] * pc[:, 1] / pc[:, 2] + K[1, 2]
        base = np.broadcast_to(np.asarray(s.color, float), (len(pc), 3)) if col is None else col[ok]
        if nrm is not None and col is None:
            nc = nrm[ok] @ R.T
            view = -pc / np.linalg.norm(pc, axis=1, keepdims=True)
            shade = 0.25 + 0.75 * np.abs(np.einsum("ij,ij->i", nc, view))
        else:
            shade = np.ones(len(pc))
        rgb = np.clip(base * shade[:, None], 0, 1)
        r = max(int(round(s.point_size / 2.0)), 0) if not hasattr(g, "triangles") else 1
        for dy in range(-r, r + 1):
            for dx in range(-r, r + 1):
                ui = np.rint(u).astype(np.int64) + dx
                vi = np.rint(v).astype(np.int64) + dy
                inside = (ui >= 0) & (ui < W) & (vi >= 0) & (vi < H)
                pix = (vi * W + ui)[inside]
                z = pc[inside, 2]
                order = np.lexsort((z, pix))
                first = np.unique(pix[order], return_index=True)[1]
                sel = order[first]
                p = pix[sel]
                closer = z[sel] < zbuf[p]
                zbuf[p[closer]] = z[sel][closer]
                img.reshape(-1, 3)[p[closer]] = rgb[inside][sel][closer]
    return np.clip(np.rint(img * 255), 0, 255).astype(np.uint8)


def _as_geometries(geoms) -> list:
    import open3d as o3d

    if isinstance(geoms, (o3d.geometry.PointCloud, o3d.geometry.TriangleMesh)):
        geoms = [geoms]
    out = []
    for i, g in enumerate(geoms):
        if not isinstance(g, (o3d.geometry.PointCloud, o3d.geometry.TriangleMesh)):
            raise ValueError(f"geometry {i}: expected an open3d PointCloud or TriangleMesh, got {type(g).__name__}")
        out.append(g)
    if not out:
        raise ValueError("nothing to render: no geometries given")
    return out


def render_geometries(geoms, *, settings: ViewSettings = ViewSettings(), camera=None) -> RenderResult:
    """Render point clouds and meshes offscreen.

    Args:
        geoms: an ``o3d.geometry.PointCloud``/``TriangleMesh`` or a list of them.
        settings: image size, view direction, colours, renderer.
        camera: (K, E) to use instead of :func:`view_camera`'s framing.

    Returns:
        A :class:`RenderResult` (RGB image and the camera).
    """
    s = settings
    if s.width < 8 or s.height < 8:
        raise ValueError(f"image size {s.width}x{s.height} is too small (need at least 8x8)")
    geoms = _as_geometries(geoms)
    K, E = view_camera(geoms, settings=s) if camera is None else (np.asarray(camera[0], float),
                                                                  np.asarray(camera[1], float))
    which = _choose_renderer(s.renderer)
    img = None
    if which in ("open3d", "auto"):
        try:
            img = _render_open3d(geoms, K, E, s)
            which = "open3d"
        except RuntimeError as e:
            if which == "open3d":
                raise RuntimeError(f"{e}. Install libvulkan1 and mesa-vulkan-drivers (Debian/Ubuntu), "
                                   "or use the software renderer (renderer='software')") from None
            log.warning("%s; falling back to the software renderer", e)
            which = "software"
    if img is None:
        img = _render_software(geoms, K, E, s)
    return RenderResult(image=img, K=K, E=E, renderer=which)


def scale_bar_mm(geoms, K: np.ndarray, E: np.ndarray, width: int) -> tuple[float, float]:
    """A scale bar for a render: (length in mm, a 1-2-5 number, and its length in
    pixels), about a fifth of the image wide at the median depth of the geometries'
    points (a perspective render: true at that depth only)."""
    pts = np.concatenate([np.asarray(g.vertices if hasattr(g, "triangles") else g.points) for g in geoms])
    z = (pts @ E[:3, :3].T + E[:3, 3])[:, 2]
    z = z[np.isfinite(z) & (z > 0)]
    if z.size == 0:
        return 0.0, 0.0
    px_per_mm = float(K[0, 0]) / float(np.median(z))
    want = 0.2 * width / px_per_mm
    e = math.floor(math.log10(want))
    mm = max(m * 10.0 ** e for m in (1, 2, 5) if m * 10.0 ** e <= want)
    return mm, mm * px_per_mm


def _draw_scale_bar(bgr: np.ndarray, mm: float, px: float, unit: str = "mm") -> None:
    """Draw a scale bar of ``px`` pixels labelled ``mm`` ``unit`` in the lower left corner (in place)."""
    import cv2

    h, w = bgr.shape[:2]
    if not (2 <= px <= w - 20) or h < 40:
        return
    ink = (0, 0, 0) if bgr[-30:, :int(px) + 20].mean() > 127 else (255, 255, 255)
    x0, y = 12, h - 14
    x1 = x0 + int(round(px))
    cv2.line(bgr, (x0, y), (x1, y), ink, 2)
    for x in (x0, x1):
        cv2.line(bgr, (x, y - 5), (x, y + 5), ink, 1)
    cv2.putText(bgr, f"{mm:g} {unit}", (x0, y - 8), cv2.FONT_HERSHEY_SIMPLEX, 0.45, ink, 1, cv2.LINE_AA)


HATCH_BGR = (150, 150, 150)
"""The hatch lines' colour on the empty pixels."""


def _hatch_empty(bgr: np.ndarray, background, label: str) -> None:
    """Diagonal grey lines over the pixels still the background colour, and a key (in place)."""
    import cv2

    bg = np.clip(np.rint(np.asarray(background, float)[::-1] * 255), 0, 255).astype(np.uint8)
    empty = np.all(bgr == bg, axis=2)
    yy, xx = np.mgrid[0:bgr.shape[0], 0:bgr.shape[1]]
    bgr[empty & ((xx + yy) % 8 == 0)] = HATCH_BGR
    ink = (0, 0, 0) if bg.mean() > 127 else (255, 255, 255)
    x0, y0 = 10, 10
    cv2.rectangle(bgr, (x0 - 4, y0 - 4), (x0 + 30 + 7 * len(label), y0 + 18), tuple(int(c) for c in bg), -1)
    sw = bgr[y0:y0 + 14, x0:x0 + 20]
    sw[:] = bg
    sy, sx = np.mgrid[0:14, 0:20]
    sw[(sx + sy) % 8 == 0] = HATCH_BGR
    cv2.rectangle(bgr, (x0, y0), (x0 + 19, y0 + 13), ink, 1)
    cv2.putText(bgr, label, (x0 + 26, y0 + 11), cv2.FONT_HERSHEY_SIMPLEX, 0.4, ink, 1, cv2.LINE_AA)


def render_to_png(geoms, path: str | os.PathLike, *, settings: ViewSettings = ViewSettings(), camera=None,
                  colorbar_spec: dict | None = None, scale_bar: bool = False,
                  length_unit: str = "mm", empty_label: str | None = None) -> RenderResult:
    """Render (see :func:`render_geometries`) and write a PNG atomically.

    ``colorbar_spec`` ({"vmin", "vmax", "cmap", "label"}) appends a colour bar, for
    geometries painted with :func:`colorize`. ``scale_bar`` draws a bar of a round
    number of millimetres in the lower left corner, true at the median depth of the
    points (:func:`scale_bar_mm`), labelled in ``length_unit``: the geometry's own ("board units"
    for a scan whose calibration stated none), never mm it is not in. A colour bar's ``categories``
    [(name, RGB), ...] draws a legend instead of a scale (:func:`colorbar`); the labels drawn are
    ``RenderResult.legend``. ``empty_label`` hatches the pixels where nothing was drawn (a view seen
    from its own camera: where it decoded nothing, e.g. a board's dark squares, which would read as
    white surface) and keys them with that label in the upper left corner.
    """
    res = render_geometries(geoms, settings=settings, camera=camera)
    bgr = np.ascontiguousarray(res.image[:, :, ::-1])
    if empty_label:
        _hatch_empty(bgr, settings.background, empty_label)
        res.empty_label = empty_label
    if scale_bar:
        res.scale_bar_mm, px = scale_bar_mm(_as_geometries(geoms), res.K, res.E, settings.width)
        _draw_scale_bar(bgr, res.scale_bar_mm, px, length_unit)
        res.scale_bar_label = f"{res.scale_bar_mm:g} {length_unit}"
    if colorbar_spec:
        bar = colorbar(res.image.shape[0], **colorbar_spec, background=settings.background)
        bgr = np.concatenate([bgr, bar], axis=1)
        res.legend = colorbar_labels(**colorbar_spec)
    write_image(path, np.ascontiguousarray(bgr))
    res.png_size = (int(bgr.shape[1]), int(bgr.shape[0]))
    return res


# ----------------------------------------------------------------------------- colour maps


# ----------------------------------------------------------------------------- 2D pictures


def read_geometry(path: str | os.PathLike):
    """Read a mesh (PLY/OBJ/STL with faces) or else a point cloud, for rendering.

    Points (vertices) with a NaN or infinite coordinate are left out, with a
    warning that counts them.

    Raises:
        FormatError: naming the file: missing, truncated (PLY), empty, or without
            a single finite point.
    """
    import open3d as o3d

    path = Path(path)
    if not path.is_file():
        raise FormatError(path, "file not found")
    geom = None
    if path.suffix.lower() in MESH_FORMATS:
        if path.suffix.lower() == ".ply":
            check_ply(path)
        with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):
            m = o3d.io.read_triangle_mesh(str(path))
        if len(m.triangles):
            geom = m
        elif path.suffix.lower() != ".ply":
            raise FormatError(path, "no triangles in the file")
    if geom is None:
        geom = read_cloud(path)
    n_in = len(geom.vertices if hasattr(geom, "triangles") else geom.points)
    geom, dropped = drop_non_finite(geom)
    if dropped:
        if dropped == n_in:
            raise FormatError(path, f"none of its {n_in} points has finite coordinates: nothing to render")
        log.warning("%s: left out %d of %d points with a NaN or infinite coordinate", path, dropped, n_in)
    if hasattr(geom, "triangles") and not geom.has_vertex_normals():
        geom.compute_vertex_normals()
    return geom
