"""The virtual rig: renders scans of procedural or loaded meshes, with ground truth (DESIGN §8).

:class:`VirtualRig` ray-traces a scene (``pipeline.scenes``) standing on the
reference plane z = 0 as the rig's camera sees it under any projector frame
(``kernels.raytrace``). :func:`simulate_scan` renders every frame of a pattern set
for one or more turntable views and writes a scan folder (DESIGN §6) plus its
ground truth:

- ``truth/object.ply``: the placed mesh at turntable angle 0 (object frame = world
  frame at angle 0);
- ``truth/<view>_depth.tiff``: float32 camera-frame depth Z_c (mm) of each pixel's
  centre ray, NaN where the ray meets nothing;
- ``truth/<view>_lit.png``: 255 where the pixel's centre sees a point lit by the
  projector image (not shadowed, facing the light), else 0;
- scan.json ``"truth"``: ``{"mesh", "reference_plane_z", "scene", "size_mm",
  "views": {name: {"depth", "lit"}}, "settings": {...}}``, plus ``"pose": {"name",
  "transform"}`` when a pose was given (``transform``: the 4x4 rigid transform from
  the upright placed scene to the posed one, which ``truth/object.ply`` holds).

Radiometry (per camera pixel, mean over sub-samples):
``I = albedo * (ambient + max(0, n.l) * lit * E(u_p, v_p))`` with E the emitted
light: each projector pixel a uniform square of ``(frame / 255)^gamma_light``,
blurred by a Gaussian (projector defocus; see :meth:`VirtualRig.emitted`), then
``recorded = full_scale * exposure * (I / (1 + ambient))^(1 / gamma_camera)`` plus
Gaussian noise, clamped and rounded.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import os
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .errors import FormatError
from .io import atomic_path, atomic_write_bytes, write_image
from .patterns import PatternSpec, frame_names, render_frame
from .rig import ParallelLight, Rig, Turntable, default_rig, turntable_transform
from .scan import Scan, View, load_scan, save_scan
from .scenes import SceneMesh, corner_normals, make_scene, pose_scene

log = logging.getLogger(__name__)

TRUTH_DIR = "truth"
EMIT_UPSAMPLE = 4

__all__ = [
    "RenderSettings",
    "VirtualRig",
    "Truth",
    "simulate_scan",
    "load_truth",
    "view_angles",
]


@dataclass(frozen=True)
class RenderSettings:
    """How the virtual rig renders (saved in scan.json ``truth.settings``)."""

    supersample: int = 2
    """Sub-samples per pixel side (S x S rays per pixel): antialiases edges and
    ring boundaries the way a real pixel integrates light; 2 is enough for
    sub-pixel boundary positions, 1 is fastest."""
    ambient: float = 0.05
    """Ambient irradiance relative to the projector's full white on a surface
    facing it: lights every visible point, shadows included (stray room light)."""
    albedo: float = 0.8
    """Diffuse (Lambertian) reflectance of the object and the plane, in (0, 1]."""
    defocus_px: float = 0.7
    """Projector defocus: Gaussian blur sigma in projector pixels (0 = sharp)."""
    noise: float = 1.5
    """Camera noise: Gaussian sigma in 8-bit grey levels (scaled by 257 for 16-bit)."""
    bit_depth: int = 8
    """Recorded bit depth: 8 or 16."""
    exposure: float = 0.9
    """Recorded fraction of full scale for full white on an albedo-1 surface facing
    the light: 0.9 leaves headroom so that lit points never saturate."""
    seed: int = 0
    """Noise seed: the same seed, scene and frames give the same images."""

    def __post_init__(self):
        def bad(field, msg):
            raise ValueError(f"RenderSettings.{field}: {msg}")

        for name in ("supersample", "bit_depth", "seed"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, np.integer)):
                bad(name, f"expected an integer, got {v!r}")
        for name in ("ambient", "albedo", "defocus_px", "noise", "exposure"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, float, np.floating, np.integer)) or not math.isfinite(v):
                bad(name, f"expected a finite number, got {v!r}")
        if not 1 <= self.supersample <= 8:
            bad("supersample", f"must be in 1..8, got {self.supersample}")
        if self.bit_depth not in (8, 16):
            bad("bit_depth", f"must be 8 or 16, got {self.bit_depth}")
        if not 0 < self.albedo <= 1:
            bad("albedo", f"must be in (0, 1], got {self.albedo}")
        if not 0 <= self.ambient <= 1:
            bad("ambient", f"must be in [0, 1], got {self.ambient}")
        if self.defocus_px < 0 or self.defocus_px > 50:
            bad("defocus_px", f"must be in [0, 50] projector pixels, got {self.defocus_px}")
        if self.noise < 0:
            bad("noise", f"must be >= 0, got {self.noise}")
        if not 0 < self.exposure <= 4:
            bad("exposure", f"must be in (0, 4], got {self.exposure}")
        if self.seed < 0:
            bad("seed", f"must be >= 0, got {self.seed}")

    @property
    def full_scale(self) -> int:
        """255 or 65535."""
        return 255 if self.bit_depth == 8 else 65535

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, d: dict) -> RenderSettings:
        """Build from a dict (unknown keys are an error naming them)."""
        known = {f.name for f in dataclasses.fields(cls)}
        extra = sorted(set(d) - known)
        if extra:
            raise ValueError(f"RenderSettings: unknown field(s) {', '.join(extra)}")
        return cls(**d)


def _turn(turntable: Turntable | None, deg: float) -> tuple[np.ndarray, np.ndarray]:
    """(R, t) of :func:`ringscan.pipeline.rig.turntable_transform`: X' = R X + t."""
    T = turntable_transform(turntable, deg)
    return T[:3, :3], T[:3, 3]


def view_angles(views: int) -> tuple[float, ...]:
    """Equal turntable steps: theta_k = k * 360 / views, k = 0..views-1."""
    if isinstance(views, bool) or not isinstance(views, (int, np.integer)) or views < 1:
        raise ValueError(f"views: expected a positive integer, got {views!r}")
    return tuple(k * 360.0 / views for k in range(int(views)))


def _pixel_gauss_weights(sigma: float, k: int) -> np.ndarray:
    """(k, 2 r + 1) float32: weight of projector pixel i0 + j at fine sample m of pixel i0.

    The fine sample sits at x = i0 + (m + 0.5) / k - 0.5; the weight is the Gaussian
    (sigma) integrated over the pixel square [i0 + j - 0.5, i0 + j + 0.5].
    """
    r = int(math.ceil(4.0 * sigma + 1.0))
    j = np.arange(-r, r + 1)
    x = (np.arange(k) + 0.5) / k - 0.5
    cdf = np.vectorize(lambda z: 0.5 * (1.0 + math.erf(z / (sigma * math.sqrt(2.0)))))
    d = x[:, None] - j[None, :]
    return (cdf(d + 0.5) - cdf(d - 0.5)).astype(np.float32)


def _mix_seed(*parts: int) -> int:
    return int(np.random.SeedSequence([int(p) for p in parts]).generate_state(1)[0]) & 0x7FFFFFFF


class VirtualRig:
    """Renders what the rig's camera sees of a scene under a projector frame.

    Args:
        rig: the rig (camera, light, turntable).
        scene: a :class:`SceneMesh`, or a scene name or mesh path for :func:`make_scene`.
        settings: rendering settings.
        device: Warp device ("cpu", "cuda:0", None = best available).
        projector_size: (W_p, H_p) of the frames; default the rig light's size
            (needed when a parallel light does not state its size).

    The geometry (ray tracing) runs once per turntable angle, lazily; each
    :meth:`render` is a cheap shading pass.
    """

    def __init__(self, rig: Rig, scene: SceneMesh | str | os.PathLike, *, settings: RenderSettings = RenderSettings(),
                 device: str | None = None, projector_size: tuple[int, int] | None = None):
        from ringscan.kernels import resolve_device
        from ringscan.kernels.geometry import make_camera, make_parallel_light, make_perspective_light

        if not isinstance(rig, Rig):
            raise ValueError(f"rig: expected a Rig, got {type(rig).__name__}")
        if not isinstance(settings, RenderSettings):
            raise ValueError(f"settings: expected RenderSettings, got {type(settings).__name__}")
        if not isinstance(scene, SceneMesh):
            scene = make_scene(scene)
        self.rig = rig
        self.scene = scene
        self.settings = settings
        self.device = resolve_device(device)
        if projector_size is None:
            projector_size = (getattr(rig.light, "width", 0), getattr(rig.light, "height", 0))
        pw, ph = (int(x) for x in projector_size)
        if pw <= 0 or ph <= 0:
            raise ValueError("projector_size: the rig's light does not state its size; pass projector_size=(W_p, H_p)")
        lw, lh = getattr(rig.light, "width", 0), getattr(rig.light, "height", 0)
        if lw and (pw, ph) != (lw, lh):
            raise ValueError(f"projector_size {pw}x{ph} does not match the rig's {lw}x{lh} light")
        self.projector_size = (pw, ph)
        c = rig.camera
        self._camera = make_camera(c.K, c.dist, c.R, c.t)
        li = rig.light
        if isinstance(li, ParallelLight):
            self._light = make_parallel_light(li.R, li.t, li.pixel_pitch_mm, li.axis_px)
        else:
            self._light = make_perspective_light(li.K, li.dist, li.R, li.t)
        self._corner = corner_normals(scene.vertices, scene.faces)
        self._deg = 0.0
        self._geometry = None
        self._calls = 0

    # -- pose

    @property
    def turntable_deg(self) -> float:
        """The current turntable angle (degrees)."""
        return self._deg

    def set_turntable(self, deg: float) -> None:
        """Turn the object to ``deg`` about the rig's turntable axis (DESIGN §6).

        The geometry is traced again on the next :meth:`render` or :meth:`truth`.
        """
        turntable_transform(self.rig.turntable, deg)  # checks the angle
        if float(deg) != self._deg:
            self._deg = float(deg)
            self._geometry = None

    def object_vertices(self) -> np.ndarray:
        """The object's vertices in the world frame at the current angle, (N, 3) float64."""
        R, t = _turn(self.rig.turntable, self._deg)
        return self.scene.vertices @ R.T + t

    def geometry(self):
        """The traced view (``kernels.raytrace.ViewGeometry``) at the current angle."""
        if self._geometry is None:
            from ringscan.kernels import raytrace

            t0 = time.perf_counter()
            R, _ = _turn(self.rig.turntable, self._deg)
            mesh = raytrace.make_trace_mesh(self.object_vertices(), self.scene.faces, self._corner @ R.T,
                                            device=self.device)
            c = self.rig.camera
            self._geometry = raytrace.trace_geometry(
                mesh, self._camera, self._light, width=c.width, height=c.height, projector_size=self.projector_size,
                supersample=self.settings.supersample, albedo=self.settings.albedo, ambient=self.settings.ambient)
            self._mesh = mesh
            import warp as wp

            wp.synchronize_device(self.device)
            log.info("traced %s at %.1f deg: %dx%d x %d sub-samples in %.2f s", self.scene.name, self._deg,
                     c.width, c.height, self.settings.supersample ** 2, time.perf_counter() - t0)
        return self._geometry

    # -- rendering

    @property
    def emitted_upsample(self) -> int:
        """k: :meth:`emitted` samples the projector image k times finer than its pixels."""
        return EMIT_UPSAMPLE if self.settings.defocus_px > 0 else 1

    def emitted(self, frame: np.ndarray) -> np.ndarray:
        """The light a projector frame emits, (H_p k, W_p k) float32 in 0..1, k = :attr:`emitted_upsample`.

        Each projector pixel emits ``(value / 255)^gamma_light`` uniformly over its
        square (a piecewise-constant image); the lens defocus blurs it with a
        Gaussian of ``settings.defocus_px``. The blurred image is evaluated exactly
        (the Gaussian integrated over each pixel square, no light from outside the
        image) at the centres of a grid k = 4 times finer than the projector's, from
        which the renderer interpolates bilinearly. Without defocus k = 1 and the
        renderer samples the sharp pixels (nearest).
        """
        import cv2

        f = np.asarray(frame)
        pw, ph = self.projector_size
        if f.shape != (ph, pw):
            raise ValueError(f"frame: expected shape ({ph}, {pw}) (the projector's), got {f.shape}")
        if f.dtype != np.uint8:
            raise ValueError(f"frame: expected uint8, got {f.dtype}")
        lut = ((np.arange(256) / 255.0) ** float(self.rig.light.gamma)).astype(np.float32)
        e = lut[f]
        if self.settings.defocus_px <= 0:
            return e
        k = EMIT_UPSAMPLE
        w = _pixel_gauss_weights(self.settings.defocus_px, k)
        tmp = np.empty((ph, pw * k), np.float32)
        for m in range(k):
            tmp[:, m::k] = cv2.filter2D(e, cv2.CV_32F, w[m][None, :], borderType=cv2.BORDER_CONSTANT)
        out = np.empty((ph * k, pw * k), np.float32)
        for m in range(k):
            out[m::k, :] = cv2.filter2D(tmp, cv2.CV_32F, w[m][:, None], borderType=cv2.BORDER_CONSTANT)
        return out

    def render(self, frame: np.ndarray, *, seed: int | None = None) -> np.ndarray:
        """The camera image under a projector frame.

        Args:
            frame: (H_p, W_p) uint8 projector frame.
            seed: noise seed; None derives one from ``settings.seed`` and a call
                counter, so successive calls get fresh noise in a repeatable order.

        Returns:
            (H, W) uint8 (8-bit) or uint16 (16-bit) image.
        """
        import warp as wp

        from ringscan.kernels import raytrace

        if seed is None:
            seed = _mix_seed(self.settings.seed, self._calls, 0x5EED)
            self._calls += 1
        elif isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
            raise ValueError(f"seed: expected a non-negative integer, got {seed!r}")
        geo = self.geometry()
        e = wp.array(self.emitted(frame), dtype=float, device=self.device)
        s = self.settings
        gamma = float(self.rig.camera.gamma)
        full_irr = (1.0 + s.ambient) / s.exposure ** gamma
        k = self.emitted_upsample
        out = raytrace.shade_frame(geo, e, full_irradiance=full_irr, upsample=k,
                                   interpolation="linear" if k > 1 else "nearest",
                                   gamma=gamma, full_scale=s.full_scale,
                                   noise_sigma=s.noise * s.full_scale / 255.0, seed=int(seed))
        img = out.numpy()
        return img.astype(np.uint8) if s.bit_depth == 8 else img

    def truth(self) -> dict:
        """Ground truth of the current view.

        Returns:
            ``depth`` (H, W) float32 camera Z_c (mm, NaN = no hit), ``lit`` (H, W) bool,
            ``points`` (H, W, 3) float32 world points (NaN = no hit), ``normals``
            (H, W, 3) float32 facet normals facing the camera (NaN = no hit).
        """
        geo = self.geometry()
        return {"depth": geo.depth.numpy(), "lit": geo.lit.numpy().astype(bool),
                "points": geo.points.numpy(), "normals": geo.normals.numpy()}


# ----------------------------------------------------------------------------- truth on disk


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
    """View name -> {"depth": relative path, "lit": relative path}."""
    settings: dict
    """The render settings used."""
    scene: str = ""
    """Scene name or mesh file stem."""

    def mesh_at(self, turntable_deg: float) -> tuple[np.ndarray, np.ndarray]:
        """The mesh in the world frame of a view at ``turntable_deg``: (vertices, faces)."""
        R, t = _turn(self.turntable, turntable_deg)
        return self.vertices @ R.T + t, self.faces

    def _file(self, view: str, key: str) -> Path:
        if view not in self.views:
            raise ValueError(f"truth: no view {view!r} (have {', '.join(self.views) or 'none'})")
        return self.folder / self.views[view][key]

    def depth(self, view: str) -> np.ndarray:
        """(H, W) float32 camera-frame depth of a view (mm), NaN where nothing was hit."""
        import cv2

        p = self._file(view, "depth")
        if not p.is_file():
            raise FormatError(p, "truth depth file not found")
        d = cv2.imread(str(p), cv2.IMREAD_UNCHANGED)
        if d is None or d.dtype != np.float32 or d.ndim != 2:
            raise FormatError(p, "not a single-channel float32 TIFF")
        return d

    def lit(self, view: str) -> np.ndarray:
        """(H, W) bool: the pixel's centre sees a point lit by the projector image."""
        from .io import read_image

        return read_image(self._file(view, "lit")) > 0


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
    src = scan.path
    t = scan.extra.get("truth")
    if not isinstance(t, dict):
        raise FormatError(src, "no 'truth' block: not a scan written by the virtual rig")
    mesh_rel = t.get("mesh")
    if not isinstance(mesh_rel, str) or ".." in Path(mesh_rel).parts or os.path.isabs(mesh_rel):
        raise FormatError(src, f"truth.mesh: bad path {mesh_rel!r}")
    mp = scan.folder / mesh_rel
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
    views = t.get("views", {})
    if not isinstance(views, dict) or not all(
            isinstance(v, dict) and isinstance(v.get("depth"), str) and isinstance(v.get("lit"), str)
            for v in views.values()):
        raise FormatError(src, "truth.views: expected {view: {\"depth\": path, \"lit\": path}}")
    for name, v in views.items():
        for key in ("depth", "lit"):
            if ".." in Path(v[key]).parts or os.path.isabs(v[key]):
                raise FormatError(src, f"truth.views.{name}.{key}: path {v[key]!r} leaves the scan folder")
    z = t.get("reference_plane_z", 0.0)
    if isinstance(z, bool) or not isinstance(z, (int, float)):
        raise FormatError(src, f"truth.reference_plane_z: expected a number, got {z!r}")
    return Truth(folder=scan.folder, vertices=vertices, faces=faces, reference_plane_z=float(z),
                 turntable=scan.rig.turntable, views=dict(views), settings=dict(t.get("settings", {})),
                 scene=str(t.get("scene", "")))


# ----------------------------------------------------------------------------- scans


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
        progress: show a tqdm progress bar.
        size_mm, up: passed to :func:`make_scene` when ``scene`` is a name or path.
        image_format: ``png`` or ``tiff`` for the frames.
        pose: turn the placed scene into this resting pose first (see
            :func:`ringscan.pipeline.scenes.pose_scene`: ``upright``, ``upside-down``,
            ``side-x``, ``side-y`` or ``AXIS:DEG[,AXIS:DEG...]``); None keeps it as it is.
            The truth mesh is the posed scene, and scan.json ``truth.pose`` records
            the transform from the upright scene.

    Returns:
        The written scan (as :func:`load_scan` reads it back).
    """
    from tqdm import tqdm

    if not isinstance(patterns, PatternSpec):
        raise ValueError(f"patterns: expected a PatternSpec, got {type(patterns).__name__}")
    if image_format not in ("png", "tiff"):
        raise ValueError(f"image_format: expected 'png' or 'tiff', got {image_format!r}")
    rig = default_rig() if rig is None else rig
    angles = view_angles(views) if views is not None else tuple(float(a) for a in turntable_deg)
    if not angles:
        raise ValueError("turntable_deg: no views")
    for a in angles:
        turntable_transform(rig.turntable, a)
    if not isinstance(scene, SceneMesh):
        scene = make_scene(scene, size_mm=size_mm, up=up)
    pose_T = None
    if pose is not None:
        scene, pose_T = pose_scene(scene, pose)
    vr = VirtualRig(rig, scene, settings=settings, device=device, projector_size=(patterns.width, patterns.height))

    folder = Path(out_dir)
    folder.mkdir(parents=True, exist_ok=True)
    mesh_rel = f"{TRUTH_DIR}/object.ply"
    _write_mesh(folder / mesh_rel, scene.vertices, scene.faces)    # empty for the plane scene
    truth = {"mesh": mesh_rel, "reference_plane_z": 0.0, "scene": scene.name, "views": {},
             "settings": settings.to_dict()}
    if pose_T is not None:
        truth["pose"] = {"name": str(pose), "transform": pose_T.tolist()}
    scan = Scan(folder=folder, rig=rig, patterns=patterns, views=(), extra={"truth": {**truth, "views": {}}})
    save_scan(scan)

    names = frame_names(patterns)
    frames = {n: render_frame(patterns, n) for n in names}
    done: list[View] = []
    t0 = time.perf_counter()
    bar = tqdm(total=len(angles) * len(names), desc=f"simulate {scene.name}", unit="frame", disable=not progress)
    try:
        for vi, deg in enumerate(angles):
            vname = f"view_{vi:03d}"
            vr.set_turntable(deg)
            rel = {}
            for fi, n in enumerate(names):
                img = vr.render(frames[n], seed=_mix_seed(settings.seed, vi, fi))
                rel[n] = f"{vname}/{n}.{image_format}"
                write_image(folder / rel[n], img)
                bar.update(1)
            tr = vr.truth()
            depth_rel, lit_rel = f"{TRUTH_DIR}/{vname}_depth.tiff", f"{TRUTH_DIR}/{vname}_lit.png"
            _write_depth(folder / depth_rel, tr["depth"])
            write_image(folder / lit_rel, np.where(tr["lit"], 255, 0).astype(np.uint8))
            truth["views"][vname] = {"depth": depth_rel, "lit": lit_rel}
            done.append(View(name=vname, turntable_deg=float(deg), frames=rel))
            snapshot = {**truth, "views": dict(truth["views"])}
            scan = dataclasses.replace(scan, views=tuple(done), extra={"truth": snapshot})
            save_scan(scan)
    finally:
        bar.close()
    log.info("simulated %d view(s) x %d frame(s) of %s in %.1f s -> %s", len(angles), len(names), scene.name,
             time.perf_counter() - t0, folder)
    return load_scan(folder)
