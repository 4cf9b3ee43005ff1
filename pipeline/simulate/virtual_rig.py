"""The virtual rig: renders scans of procedural or loaded meshes, with ground truth (docs/design.md §16).

:class:`VirtualRig` ray-traces a scene (``pipeline.simulate.scenes``) standing on the
reference plane z = 0 as the rig's camera sees it under any projector frame
(``kernels.raytrace``). :func:`simulate_scan` renders every frame of a pattern set
for one or more turntable views and writes a scan folder (docs/design.md §11) plus its
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

import numpy as np

from ringscan.kernels import raytrace, resolve_device
from ringscan.kernels.geometry import make_camera, make_parallel_light, make_perspective_light
from ringscan.pipeline.formats.rig import ParallelLight, Rig, Turntable, turntable_transform
from ringscan.pipeline.simulate.scenes import SceneMesh, corner_normals, make_scene

log = logging.getLogger(__name__)

EMIT_UPSAMPLE = 4
_FILTER_ALIGN = 64
"""The blur of a window of the projector's image reads columns from a multiple of this many pixels
(see VirtualRig._emitted_window)."""

__all__ = ["EMIT_UPSAMPLE", "RenderSettings", "view_angles", "VirtualRig"]


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
    """(R, t) of :func:`ringscan.pipeline.formats.rig.turntable_transform`: X' = R X + t."""
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


_CORNER_NORMALS: dict = {}
_CORNER_NORMALS_KEPT = 8


def _corner_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """:func:`corner_normals` of a mesh, computed once for the last few meshes (keyed by their bytes): the
    rigs of a two-camera scan, and scan after scan of the same scene, share them (the sphere's 82k faces take
    ~0.3 s, the terrain's 116k ~1 s). Read-only: every caller gets the same array."""
    import hashlib

    v = np.ascontiguousarray(vertices)
    f = np.ascontiguousarray(faces)
    key = (v.shape, v.dtype.str, f.shape, f.dtype.str,
           hashlib.sha1(v.tobytes()).hexdigest(), hashlib.sha1(f.tobytes()).hexdigest())
    cn = _CORNER_NORMALS.pop(key, None)
    if cn is None:
        cn = corner_normals(v, f)
        cn.flags.writeable = False
    _CORNER_NORMALS[key] = cn  # the most recently used last
    while len(_CORNER_NORMALS) > _CORNER_NORMALS_KEPT:
        del _CORNER_NORMALS[next(iter(_CORNER_NORMALS))]
    return cn


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
        self._corner = _corner_normals(scene.vertices, scene.faces)
        self._deg = 0.0
        self._geometry = None
        self._window = None
        self._emit_buf = None
        self._calls = 0

    # -- pose

    @property
    def turntable_deg(self) -> float:
        """The current turntable angle (degrees)."""
        return self._deg

    def set_turntable(self, deg: float) -> None:
        """Turn the object to ``deg`` about the rig's turntable axis (docs/design.md §11).

        The geometry is traced again on the next :meth:`render` or :meth:`truth`.
        """
        turntable_transform(self.rig.turntable, deg)  # checks the angle
        if float(deg) != self._deg:
            self._deg = float(deg)
            self._geometry = None
            self._window = None

    def object_vertices(self) -> np.ndarray:
        """The object's vertices in the world frame at the current angle, (N, 3) float64."""
        R, t = _turn(self.rig.turntable, self._deg)
        return self.scene.vertices @ R.T + t

    def geometry(self):
        """The traced view (``kernels.raytrace.ViewGeometry``) at the current angle."""
        if self._geometry is None:

            t0 = time.perf_counter()
            R, _ = _turn(self.rig.turntable, self._deg)
            mesh = raytrace.make_trace_mesh(self.object_vertices(), self.scene.faces, self._corner @ R.T,
                                            device=self.device, face_albedo=self.scene.face_albedo)
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
        pw, ph = self.projector_size
        return self._emitted_window(self._check_frame(frame), (0, 0, pw, ph))

    def _check_frame(self, frame: np.ndarray) -> np.ndarray:
        f = np.asarray(frame)
        pw, ph = self.projector_size
        if f.shape != (ph, pw):
            raise ValueError(f"frame: expected shape ({ph}, {pw}) (the projector's), got {f.shape}")
        if f.dtype != np.uint8:
            raise ValueError(f"frame: expected uint8, got {f.dtype}")
        return f

    def _emitted_window(self, f: np.ndarray, window: tuple[int, int, int, int]) -> np.ndarray:
        """:meth:`emitted` of the projector pixels ``[x0, x1) x [y0, y1)`` alone, ((y1 - y0) k, (x1 - x0) k).

        The blur reaches r projector pixels (the weights' half width), so the frame is read
        r pixels beyond the window on each side (as far as the image goes; beyond it the
        light is 0, as for the whole image): every value is computed from the same
        pixels and weights as over the whole image.
        """
        import cv2

        x0, y0, x1, y1 = window
        lut = ((np.arange(256) / 255.0) ** float(self.rig.light.gamma)).astype(np.float32)
        if self.settings.defocus_px <= 0:
            return lut[f[y0:y1, x0:x1]]
        pw, ph = self.projector_size
        k = EMIT_UPSAMPLE
        w = _pixel_gauss_weights(self.settings.defocus_px, k)
        r = (w.shape[1] - 1) // 2
        # The crop's columns start at a multiple of _FILTER_ALIGN and end at one or at the image's edge:
        # OpenCV's filter runs a row in vector blocks and its last pixels (the blocks' remainder) by
        # another path, which rounds differently in the last bit; aligned so, every pixel takes the path
        # it takes over the whole image (the remainder is the image's own, where the crop reaches it).
        cx0 = max(x0 - r, 0) // _FILTER_ALIGN * _FILTER_ALIGN
        cx1 = min(cx0 - (cx0 - min(x1 + r, pw)) // _FILTER_ALIGN * _FILTER_ALIGN, pw)
        cy0, cy1 = max(y0 - r, 0), min(y1 + r, ph)
        e = lut[f[cy0:cy1, cx0:cx1]]
        wd = cx1 - cx0
        h = e.shape[0]
        tmp = np.empty((h, wd * k), np.float32)
        for m in range(k):
            tmp[:, m::k] = cv2.filter2D(e, cv2.CV_32F, w[m][None, :], borderType=cv2.BORDER_CONSTANT)
        out = np.empty((h * k, wd * k), np.float32)
        for m in range(k):
            rows = out[m::k, :]  # written in place (whole rows, every k-th): no copy of the image
            got = cv2.filter2D(tmp, cv2.CV_32F, w[m][:, None], dst=rows, borderType=cv2.BORDER_CONSTANT)
            if not np.shares_memory(got, rows):
                rows[...] = got
        return out[(y0 - cy0) * k:(y1 - cy0) * k, (x0 - cx0) * k:(x1 - cx0) * k]

    def emit_window(self) -> tuple[int, int, int, int]:
        """(x0, y0, x1, y1): the projector pixels ``[x0, x1) x [y0, y1)`` whose light the camera can see
        at the current angle: every sub-sample that the projector may light (a direct weight > 0, on
        the image) falls in it, with one pixel to spare on every side for the bilinear
        interpolation between fine samples (or the image's edge). :meth:`render` computes the
        emitted light of this window alone: a camera that sees a part of the projector's image
        renders in a fraction of the time, with the same frames. (0, 0, 0, 0) when the projector
        lights nothing the camera sees.
        """
        if self._window is None:
            s = self.geometry().samples.numpy()
            pw, ph = self.projector_size
            u, v = s[:, 0], s[:, 1]
            # a superset of the kernel's inside_image test (u in [-0.5, W_p - 0.5]): never too small
            on = (s[:, 2] > 0) & (u >= -1.0) & (u <= pw) & (v >= -1.0) & (v <= ph)
            if not on.any():
                self._window = (0, 0, 0, 0)
            else:
                u, v = u[on], v[on]
                self._window = (max(int(np.floor(u.min())) - 1, 0), max(int(np.floor(v.min())) - 1, 0),
                                min(int(np.ceil(u.max())) + 2, pw), min(int(np.ceil(v.max())) + 2, ph))
        return self._window

    def _emitted_for_render(self, frame: np.ndarray) -> np.ndarray:
        """The emitted image as :meth:`render` uses it: the whole (H_p k, W_p k) image, computed over
        :meth:`emit_window` alone and 0 elsewhere (light the camera cannot see): one buffer, reused
        from frame to frame (a new image a frame where the window is the whole image)."""
        f = self._check_frame(frame)
        pw, ph = self.projector_size
        k = self.emitted_upsample
        x0, y0, x1, y1 = win = self.emit_window()
        if win == (0, 0, pw, ph):  # the camera sees the whole image: computed in place, nothing to copy
            self._emit_buf = None
            return np.ascontiguousarray(self._emitted_window(f, win))
        if self._emit_buf is None or self._emit_buf[0] != win:
            self._emit_buf = (win, np.zeros((ph * k, pw * k), np.float32))
        buf = self._emit_buf[1]
        if x1 > x0 and y1 > y0:
            buf[y0 * k:y1 * k, x0 * k:x1 * k] = self._emitted_window(f, win)
        return buf

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


        if seed is None:
            seed = _mix_seed(self.settings.seed, self._calls, 0x5EED)
            self._calls += 1
        elif isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
            raise ValueError(f"seed: expected a non-negative integer, got {seed!r}")
        geo = self.geometry()
        # on the CPU the kernel reads the buffer where it is (no copy of the whole image a frame)
        e = wp.array(self._emitted_for_render(frame), dtype=float, device=self.device,
                     copy=wp.get_device(self.device).is_cuda)
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


# ----------------------------------------------------------------------------- scans


