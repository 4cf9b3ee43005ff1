"""A second, independent renderer for the virtual rig: Mitsuba 3 (``ringscan simulate --renderer mitsuba``).

ringscan's own renderer (:mod:`.virtual_rig`, ``kernels/raytrace.py``) shares the
reconstruction's camera and light geometry, so its scans can show self-consistency
only (docs/design.md §16). This renderer takes from ringscan the rig's numbers (camera
K, distortion, R, t, size; the light's), the scene as :func:`.scan.prepare_scene`
places it, and the scan/truth writing of :func:`.scan.simulate_scan`; everything
between — rays, intersections, the projector's light, shadows, inter-reflections,
the truth depth and lit mask — is Mitsuba's (path tracing) and OpenCV's (lens
distortion), none of ringscan's projection, ray or light code.

How a frame is made (docs/virtual_rig.md, "An independent renderer: Mitsuba 3"):

- The scene is rendered in the light's frame (a perspective projector's OpenCV frame,
  a parallel light's frame L), so that the light sits at an exactly representable
  place in Mitsuba's float32 world.
- The light is Mitsuba's ``projector`` emitter (a pinhole with a texture). Its texture
  is the frame through the light's response, ``(value / 255)^gamma_light``, blurred by
  a Gaussian of ``defocus_px`` projector pixels on a grid 4x finer than the projector's
  (Mitsuba's projector cannot defocus), laid out on the projector's *ideal* (undistorted)
  image: the projector's lens distortion is applied by resampling the frame with
  OpenCV's ``projectPoints``; the principal point, both focal lengths and the skew go
  into the texture's affine ``to_uv``. A parallel light (an orthographic projector,
  which Mitsuba does not have) is a projector 100 km away along its axis with the
  focal length that gives the light's pixel pitch at the reference plane: its rays
  differ from parallel by less than 1e-3 projector pixels over the working volume.
- The projector's irradiance falls off as 1 / z_p^2 (physics, which ringscan's own
  renderer leaves out); its scale makes full white at the depth of the scene's centre
  equal to ringscan's full white (irradiance 1 on a surface facing the light).
- Ambient light (``RenderSettings.ambient``) is Mitsuba's ``constant`` environment of
  that radiance, occluded and inter-reflected like real room light; since light adds,
  it is rendered once per view (``ambient_spp`` samples a texel) and added to every
  frame, which then carries the projector alone (no emitter-selection noise).
- The camera is Mitsuba's ``perspective`` sensor on a canvas of the camera's *ideal*
  image, S x S texels a camera pixel (S = ``RenderSettings.supersample``), ``spp``
  random samples a texel (box filter), ``path`` integrator to ``max_depth``; each
  camera pixel is the mean of S x S sub-samples at ((i + 1/2) / S - 1/2) about its
  centre, each undistorted with OpenCV (``undistortPoints``) and read bilinearly from
  the canvas (exactly a texel centre where the camera has no distortion).
- Then the camera model of ringscan's virtual rig: response ``gamma`` of the rig's
  camera, ``exposure``, Gaussian noise in grey levels, rounding and clamping.

Surfaces are two-sided Lambertian (Mitsuba's ``diffuse``) with flat facets (no
interpolated normals); the reference plane z = 0 is a 200 m square. Glossy parts
(``MitsubaSettings.coat_roughness``) are Mitsuba's ``roughplastic``: the albedo's
diffuse base under a clear coat whose GGX lobe reflects the projector as a highlight
(the plane stays matte).

Truth (per view): each camera pixel's centre ray (OpenCV undistortion) is intersected
with the Mitsuba scene (``Scene.ray_intersect``): the depth is its camera Z; the pixel
is lit where the hit faces the light (facet normal turned toward the camera), a
shadow ray toward the projector's centre (``Scene.ray_test``) meets nothing, and the
point projects (OpenCV ``projectPoints``, or the parallel light's x_L / s + a_u)
inside the projector image.

Mitsuba is imported only when a :class:`MitsubaRig` is made (``pip install
'ringscan[mitsuba]'``).
"""

from __future__ import annotations

import dataclasses
import glob
import logging
import math
import os
import re
import time
from dataclasses import dataclass

import numpy as np

from ringscan.pipeline.formats.errors import RingscanError
from ringscan.pipeline.formats.rig import ParallelLight, PerspectiveLight, Rig, turntable_transform
from ringscan.pipeline.simulate.scenes import SceneMesh, make_scene
from ringscan.pipeline.simulate.virtual_rig import RenderSettings

log = logging.getLogger(__name__)

__all__ = ["MitsubaSettings", "MitsubaRig", "MitsubaMissing", "INSTALL_HINT", "MIN_LLVM", "mitsuba_available",
           "choose_variant", "PARALLEL_DISTANCE_MM", "PLANE_HALF_MM", "COAT_IOR"]

INSTALL_HINT = "pip install 'ringscan[mitsuba]'"
"""How to install Mitsuba 3 for ringscan."""

MIN_LLVM = 19
"""Oldest libLLVM major version the LLVM variant is used with. Dr.Jit 1.5 (Mitsuba 3.9)
aborts the process on LLVM 14, 15 and 16 ("LLVM ERROR: Cannot select: fminimum"); 19 works
(17 and 18 were not tried)."""

PARALLEL_DISTANCE_MM = 1.0e8
"""A parallel light is rendered as a projector this far (100 km) along its axis. Its rays
meet the reference plane's pixels exactly; at height z they are displaced by
(x_L / s) z / D projector pixels: 5e-4 px at 500 px from the axis and z = 100 mm."""

PLANE_HALF_MM = 1.0e5
"""Half the side of the square that stands for the infinite reference plane (mm). Its
central +-1 m is its own pair of triangles, so that the plane near the object is not
interpolated from vertices 100 m away (float32: their rounding would tilt it by µm)."""

COAT_IOR = 1.49
"""Refractive index of a glossy part's clear coat (:attr:`MitsubaSettings.coat_roughness`): acrylic,
polypropylene (Mitsuba's ``roughplastic`` default)."""

_PLANE_INNER_MM = 1000.0
_EMIT_UPSAMPLE = 4
_MAX_ALBEDO_GROUPS = 256
_FLIP = np.diag([-1.0, -1.0, 1.0])  # OpenCV's camera axes (x right, y down) -> Mitsuba's (x left, y up)


@dataclass(frozen=True)
class MitsubaSettings:
    """How Mitsuba renders (beyond :class:`RenderSettings`, whose meaning it keeps);
    saved in scan.json ``truth.renderer``."""

    spp: int = 4
    """Samples a canvas texel (random positions in it, box filter); a camera pixel gets
    S x S texels, so S^2 * spp samples (S = ``RenderSettings.supersample``)."""
    max_depth: int = 3
    """Longest light path (Mitsuba's ``path`` integrator): 2 is direct light only, 3 adds one
    bounce (the object lighting the plane and back), -1 is unlimited."""
    ambient_spp: int = 4
    """Samples a texel of the ambient image, rendered once per view and added to every frame (its
    Monte Carlo noise is the same in every frame: an ambient of 0.05 at 4 spp varies by ~0.1 % of
    full white)."""
    coat_roughness: float | None = None
    """Glossy parts ("my parts are glossy"): None (default) renders the object matte (Lambertian,
    Mitsuba's ``diffuse``); a number renders it as glossy plastic, Mitsuba's ``roughplastic``: a
    diffuse base of the render's albedo under a clear coat (index 1.49) whose specular lobe has this
    GGX roughness alpha in [0.01, 1] (0.05: polished, 0.1: glossy, 0.3: satin). The reference plane
    stays matte. ringscan's own renderer has no specular lobe; this is Mitsuba's only."""
    variant: str | None = None
    """Mitsuba variant; None: ``llvm_ad_rgb`` where Dr.Jit has a libLLVM of at least
    :data:`MIN_LLVM` (vectorised, ~5x faster here), else ``scalar_rgb``."""

    def __post_init__(self):
        def bad(field, msg):
            raise ValueError(f"MitsubaSettings.{field}: {msg}")

        for name in ("spp", "max_depth", "ambient_spp"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, np.integer)):
                bad(name, f"expected an integer, got {v!r}")
        if not 1 <= self.spp <= 4096:
            bad("spp", f"must be in 1..4096, got {self.spp}")
        if not 1 <= self.ambient_spp <= 4096:
            bad("ambient_spp", f"must be in 1..4096, got {self.ambient_spp}")
        if self.max_depth != -1 and not 2 <= self.max_depth <= 64:
            bad("max_depth", f"must be -1 (unlimited) or in 2..64, got {self.max_depth}")
        if self.coat_roughness is not None:
            v = self.coat_roughness
            if isinstance(v, bool) or not isinstance(v, (int, float, np.floating, np.integer)) or not math.isfinite(v):
                bad("coat_roughness", f"expected None (matte) or a finite number, got {v!r}")
            if not 0.01 <= v <= 1.0:
                bad("coat_roughness", f"must be in [0.01, 1] (a GGX alpha), got {v}")
        if self.variant is not None and self.variant not in ("scalar_rgb", "llvm_ad_rgb", "cuda_ad_rgb"):
            bad("variant", f"expected scalar_rgb, llvm_ad_rgb or cuda_ad_rgb, got {self.variant!r}")

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)


# ----------------------------------------------------------------------------- Mitsuba and its variant


class MitsubaMissing(RingscanError, ImportError):
    """Mitsuba 3 is not installed (the message says how to install it)."""

    def __init__(self):
        super().__init__(f"the Mitsuba renderer needs Mitsuba 3, which is not installed: {INSTALL_HINT}")


def mitsuba_available() -> bool:
    """Whether Mitsuba 3 can be imported (without importing it)."""
    import importlib.util

    return importlib.util.find_spec("mitsuba") is not None


def _import_mitsuba():
    try:
        import mitsuba
    except ImportError:
        raise MitsubaMissing() from None
    return mitsuba


def _find_libllvm() -> str | None:
    """The newest libLLVM of at least :data:`MIN_LLVM` in the usual places, or None."""
    best = None
    pats = ["/usr/lib/*/libLLVM*.so*", "/usr/lib/libLLVM*.so*", "/usr/lib/llvm-*/lib/libLLVM*.so*",
            "/usr/local/lib/libLLVM*.so*"]
    for pat in pats:
        for p in glob.glob(pat):
            m = re.search(r"libLLVM(?:-|\.so\.)(\d+)", os.path.basename(p))
            if m and int(m.group(1)) >= MIN_LLVM and (best is None or int(m.group(1)) > best[0]):
                best = (int(m.group(1)), p)
    return best[1] if best else None


def choose_variant(requested: str | None = None) -> str:
    """Set and return the Mitsuba variant: ``requested``, or ``llvm_ad_rgb`` where Dr.Jit
    loads a libLLVM of at least :data:`MIN_LLVM`, else ``scalar_rgb``.

    Unless ``DRJIT_LIBLLVM_PATH`` is set, it is set (before Mitsuba is first imported) to
    the newest such libLLVM found in the system's library folders (Debian: ``libllvm19``).

    Raises:
        MitsubaMissing: Mitsuba is not installed.
        ValueError: ``requested`` is not a variant of the installed Mitsuba.
    """
    if "DRJIT_LIBLLVM_PATH" not in os.environ:
        path = _find_libllvm()
        if path:
            os.environ["DRJIT_LIBLLVM_PATH"] = path
    mi = _import_mitsuba()
    if requested is not None:
        if requested not in mi.variants():
            raise ValueError(f"Mitsuba variant {requested!r} is not available (have {', '.join(mi.variants())})")
        mi.set_variant(requested)
        return requested
    if "llvm_ad_rgb" in mi.variants():
        try:
            mi.set_variant("llvm_ad_rgb")
            import drjit as dr

            version = dr.detail.llvm_version()
            if int(version[0]) >= MIN_LLVM:
                return "llvm_ad_rgb"
            log.info("Mitsuba: libLLVM %s is older than %d (Dr.Jit aborts on it): using scalar_rgb",
                     ".".join(str(x) for x in version), MIN_LLVM)
        except Exception as e:  # no libLLVM at all, or a Dr.Jit without llvm_version
            log.info("Mitsuba: the LLVM variant is not usable (%s): using scalar_rgb", e)
    mi.set_variant("scalar_rgb")
    return "scalar_rgb"


# ----------------------------------------------------------------------------- the rig's geometry, read


def _normalized_from_pixels(K: np.ndarray, dist: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """(N, 2) float64 ideal normalized coordinates of observed pixel positions (OpenCV's
    iterative undistortion; K's skew taken off by hand, since OpenCV's undistortion ignores it)."""
    import cv2

    fx, s, cx, fy, cy = K[0, 0], K[0, 1], K[0, 2], K[1, 1], K[1, 2]
    yd = (uv[:, 1] - cy) / fy
    xd = (uv[:, 0] - cx - s * yd) / fx
    pts = np.stack([xd, yd], -1).reshape(-1, 1, 2)
    if not np.any(dist):
        return pts.reshape(-1, 2)
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 200, 1e-15)
    out = np.empty_like(pts)
    step = 1 << 20  # OpenCV's point count is an int; chunks also keep its buffers small
    for i in range(0, len(pts), step):
        out[i:i + step] = cv2.undistortPoints(pts[i:i + step], np.eye(3), np.asarray(dist, np.float64), None, None,
                                              criteria=crit)
    return out.reshape(-1, 2)


def _pixels_from_normalized(K: np.ndarray, dist: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """(N, 2) pixel positions of ideal normalized coordinates (OpenCV's ``projectPoints``
    distortion; K, skew included, applied by hand)."""
    import cv2

    xy = np.asarray(xy, np.float64).reshape(-1, 2)
    if np.any(dist):
        pts = np.concatenate([xy, np.ones((len(xy), 1))], 1).reshape(-1, 1, 3)
        d, _ = cv2.projectPoints(pts, np.zeros(3), np.zeros(3), np.eye(3), np.asarray(dist, np.float64))
        xy = d.reshape(-1, 2)
    u = K[0, 0] * xy[:, 0] + K[0, 1] * xy[:, 1] + K[0, 2]
    v = K[1, 1] * xy[:, 1] + K[1, 2]
    return np.stack([u, v], -1)


@dataclass(frozen=True)
class _Light:
    """The light as the Mitsuba scene has it: the frame M the scene is rendered in
    (X_M = R X_w + t), the projector's pose in M, and its pixel mapping."""

    R: np.ndarray
    t: np.ndarray
    to_world: np.ndarray  # 4x4: Mitsuba projector local -> M
    position: np.ndarray  # projector centre in M
    K: np.ndarray  # pixel mapping of the projector's ideal normalized coordinates (OpenCV's frame)
    dist: np.ndarray
    parallel: ParallelLight | None
    size: tuple[int, int]
    gamma: float


def _light_of(rig: Rig, projector_size: tuple[int, int]) -> _Light:
    li = rig.light
    if isinstance(li, PerspectiveLight):
        T = np.eye(4)
        T[:3, :3] = _FLIP
        return _Light(R=np.asarray(li.R, float), t=np.asarray(li.t, float), to_world=T, position=np.zeros(3),
                      K=np.asarray(li.K, float), dist=np.asarray(li.dist, float), parallel=None,
                      size=projector_size, gamma=float(li.gamma))
    if isinstance(li, ParallelLight):
        # A projector at (0, 0, D) in the light frame L looking down -z_L: its OpenCV axes are
        # x_p = x_L, y_p = -y_L, z_p = -z_L, so u = (D / s) x + a_u, v = -(D / s) y + a_v on z_L = 0.
        D = PARALLEL_DISTANCE_MM
        T = np.eye(4)
        T[:3, :3] = np.diag([1.0, -1.0, -1.0]) @ _FLIP
        T[:3, 3] = [0.0, 0.0, D]
        f = D / float(li.pixel_pitch_mm)
        K = np.array([[f, 0.0, li.axis_px[0]], [0.0, -f, li.axis_px[1]], [0.0, 0.0, 1.0]])
        return _Light(R=np.asarray(li.R, float), t=np.asarray(li.t, float), to_world=T, position=np.array([0, 0, D]),
                      K=K, dist=np.zeros(5), parallel=li, size=projector_size, gamma=float(li.gamma))
    raise ValueError(f"rig: the Mitsuba renderer needs a calibrated light (perspective or parallel), "
                     f"got {getattr(li, 'model', type(li).__name__)!r}")


# ----------------------------------------------------------------------------- the renderer


class MitsubaRig:
    """Renders what the rig's camera sees of a scene under a projector frame, with Mitsuba 3.

    The same interface as :class:`~ringscan.pipeline.simulate.virtual_rig.VirtualRig`
    where :func:`~ringscan.pipeline.simulate.scan.simulate_scan` uses it: ``rig``,
    :meth:`set_turntable`, :meth:`render`, :meth:`truth`.

    Args:
        rig: the rig (camera, calibrated light, turntable).
        scene: a :class:`SceneMesh`, or a scene name or mesh path for :func:`make_scene`.
        settings: ringscan's render settings (their meaning kept: see the module docstring).
        mitsuba: Mitsuba's own settings.
        projector_size: (W_p, H_p) of the frames; default the rig light's size.

    Raises:
        MitsubaMissing: Mitsuba is not installed.
        ValueError: a bad rig, scene, setting or size.
    """

    def __init__(self, rig: Rig, scene: SceneMesh | str | os.PathLike, *,
                 settings: RenderSettings = RenderSettings(), mitsuba: MitsubaSettings = MitsubaSettings(),
                 projector_size: tuple[int, int] | None = None):
        if not isinstance(rig, Rig):
            raise ValueError(f"rig: expected a Rig, got {type(rig).__name__}")
        if not isinstance(settings, RenderSettings):
            raise ValueError(f"settings: expected RenderSettings, got {type(settings).__name__}")
        if not isinstance(mitsuba, MitsubaSettings):
            raise ValueError(f"mitsuba: expected MitsubaSettings, got {type(mitsuba).__name__}")
        if not isinstance(scene, SceneMesh):
            scene = make_scene(scene)
        if projector_size is None:
            projector_size = (getattr(rig.light, "width", 0), getattr(rig.light, "height", 0))
        pw, ph = (int(x) for x in projector_size)
        if pw <= 0 or ph <= 0:
            raise ValueError("projector_size: the rig's light does not state its size; pass projector_size=(W_p, H_p)")
        lw, lh = getattr(rig.light, "width", 0), getattr(rig.light, "height", 0)
        if lw and (pw, ph) != (lw, lh):
            raise ValueError(f"projector_size {pw}x{ph} does not match the rig's {lw}x{lh} light")
        self._light = _light_of(rig, (pw, ph))
        if scene.face_albedo is not None and len(np.unique(scene.face_albedo)) > _MAX_ALBEDO_GROUPS:
            raise ValueError(f"scene {scene.name!r}: the Mitsuba renderer takes at most {_MAX_ALBEDO_GROUPS} "
                             "distinct face albedos (one Mitsuba mesh each)")
        self.variant = choose_variant(mitsuba.variant)
        import mitsuba as mi

        self._mi = mi
        self.rig = rig
        self.scene = scene
        self.settings = settings
        self.mitsuba = mitsuba
        self.projector_size = (pw, ph)
        self._deg = 0.0
        self._view = None
        self._calls = 0
        self._setup_camera()
        self._setup_projector()

    # -- what it is

    def describe(self) -> dict:
        """scan.json ``truth.renderer``: the renderer, Mitsuba's version, variant and settings."""
        return {**self.mitsuba.to_dict(), "name": "mitsuba", "version": str(self._mi.__version__),
                "variant": self.variant,
                "parallel_distance_mm": PARALLEL_DISTANCE_MM if self._light.parallel is not None else None}

    # -- pose

    @property
    def turntable_deg(self) -> float:
        """The current turntable angle (degrees)."""
        return self._deg

    def set_turntable(self, deg: float) -> None:
        """Turn the object to ``deg`` about the rig's turntable axis; the Mitsuba scene is
        built again on the next :meth:`render` or :meth:`truth`."""
        turntable_transform(self.rig.turntable, deg)  # checks the angle
        if float(deg) != self._deg:
            self._deg = float(deg)
            self._view = None

    def object_vertices(self) -> np.ndarray:
        """The object's vertices in the world frame at the current angle, (N, 3) float64."""
        T = turntable_transform(self.rig.turntable, self._deg)
        return self.scene.vertices @ T[:3, :3].T + T[:3, 3]

    # -- the camera's canvas and the projector's texture (once)

    def _setup_camera(self) -> None:
        c = self.rig.camera
        S = self.settings.supersample
        K = np.asarray(c.K, float)
        fx, cx, cy = K[0, 0], K[0, 2], K[1, 2]
        # sub-sample positions of every pixel, their ideal normalized coordinates
        off = (np.arange(S) + 0.5) / S - 0.5
        us = (np.arange(c.width)[:, None] + off[None, :]).ravel()   # (W S,)
        vs = (np.arange(c.height)[:, None] + off[None, :]).ravel()  # (H S,)
        U, V = np.meshgrid(us, vs)
        xy = _normalized_from_pixels(K, c.dist, np.stack([U.ravel(), V.ravel()], -1))
        # the canvas: square texels of 1 / (S fx) in normalized coordinates; canvas pseudo-pixel
        # u' = fx x + cx, v' = fx y + cy, texel (col, row) centre at u' = u0 - 1/2 + (col + 1/2) / S
        up = fx * xy[:, 0] + cx
        vp = fx * xy[:, 1] + cy
        u0, v0 = int(math.floor(up.min())) - 1, int(math.floor(vp.min())) - 1
        u1, v1 = int(math.ceil(up.max())) + 1, int(math.ceil(vp.max())) + 1
        Wc, Hc = (u1 - u0 + 1) * S, (v1 - v0 + 1) * S
        self._map_x = (S * (up - u0 + 0.5) - 0.5).astype(np.float32).reshape(c.height * S, c.width * S)
        self._map_y = (S * (vp - v0 + 0.5) - 0.5).astype(np.float32).reshape(c.height * S, c.width * S)
        self._canvas = (Wc, Hc)
        self._fov = math.degrees(2.0 * math.atan(Wc / (2.0 * S * fx)))
        self._ppo = (0.5 - (cx - u0 + 0.5) * S / Wc, 0.5 - (cy - v0 + 0.5) * S / Hc)
        # the centre rays of the truth
        uu, vv = np.meshgrid(np.arange(c.width, dtype=float), np.arange(c.height, dtype=float))
        self._centre_xy = _normalized_from_pixels(K, c.dist, np.stack([uu.ravel(), vv.ravel()], -1))

    def _setup_projector(self) -> None:
        L = self._light
        pw, ph = self.projector_size
        s = self.settings
        distorted = bool(np.any(L.dist))
        self._k = k = _EMIT_UPSAMPLE if (s.defocus_px > 0 or distorted) else 1
        # the emitted image: fine grid (k per projector pixel), padded by a margin of zeros that
        # holds the defocus blur's tail and leaves a zero rim (clamped lookups outside are dark)
        # (a whole number of projector pixels, so that the fine grid stays on the projector's pixel grid)
        self._pad = pad = k * int(math.ceil((4.0 * s.defocus_px * k + 2.0) / k))
        fw, fh = pw * k + 2 * pad, ph * k + 2 * pad
        # the texture: the projector's ideal image, texel (i, j) centre at ideal pixel
        # (U0 - 1/2 + (i + 1/2) / k, V0 - 1/2 + (j + 1/2) / k)
        if distorted:
            t = np.linspace(0.0, 1.0, 64)
            border = np.concatenate([np.stack([-0.5 + pw * t, np.full(64, -0.5)], -1),
                                     np.stack([-0.5 + pw * t, np.full(64, ph - 0.5)], -1),
                                     np.stack([np.full(64, -0.5), -0.5 + ph * t], -1),
                                     np.stack([np.full(64, pw - 0.5), -0.5 + ph * t], -1)])
            ideal = _pixels_from_normalized(L.K, np.zeros(5), _normalized_from_pixels(L.K, L.dist, border))
            m = pad / k + 1.0
            U0 = int(math.floor(min(ideal[:, 0].min(), -0.5) - m))
            V0 = int(math.floor(min(ideal[:, 1].min(), -0.5) - m))
            U1 = int(math.ceil(max(ideal[:, 0].max(), pw - 0.5) + m))
            V1 = int(math.ceil(max(ideal[:, 1].max(), ph - 0.5) + m))
            Wt, Ht = (U1 - U0) * k, (V1 - V0) * k
            ii, jj = np.meshgrid(U0 - 0.5 + (np.arange(Wt) + 0.5) / k, V0 - 0.5 + (np.arange(Ht) + 0.5) / k)
            y = (jj.ravel() - L.K[1, 2]) / L.K[1, 1]
            x = (ii.ravel() - L.K[0, 2] - L.K[0, 1] * y) / L.K[0, 0]
            dp = _pixels_from_normalized(L.K, L.dist, np.stack([x, y], -1))
            # the fine-grid index of projector pixel coordinate u is k (u + 1/2) - 1/2 + pad
            self._tex_map = ((k * (dp[:, 0] + 0.5) - 0.5 + pad).astype(np.float32).reshape(Ht, Wt),
                             (k * (dp[:, 1] + 0.5) - 0.5 + pad).astype(np.float32).reshape(Ht, Wt))
        else:  # the texture is the padded fine grid itself
            U0 = V0 = -pad // k
            Wt, Ht = fw, fh
            self._tex_map = None
        self._fine = (fw, fh)
        self._tex = (Wt, Ht)
        # the projector's frustum in normalized coordinates must hold the whole texture:
        # tan_x >= |x| and tan_y = tan_x Ht / Wt >= |y| at the texture's corners
        corners = np.array([[U0 - 0.5, V0 - 0.5], [U0 - 0.5 + Wt / k, V0 - 0.5],
                            [U0 - 0.5, V0 - 0.5 + Ht / k], [U0 - 0.5 + Wt / k, V0 - 0.5 + Ht / k]])
        cy_ = (corners[:, 1] - L.K[1, 2]) / L.K[1, 1]
        cx_ = (corners[:, 0] - L.K[0, 2] - L.K[0, 1] * cy_) / L.K[0, 0]
        tan_x = 1.02 * max(np.abs(cx_).max(), np.abs(cy_).max() * Wt / Ht)
        tan_y = tan_x * Ht / Wt
        self._proj_fov = math.degrees(2.0 * math.atan(tan_x))
        # frustum uv -> texture uv: x = (2 a - 1) tan_x, y = (2 b - 1) tan_y; texel coordinate
        # i + 1/2 = k (u - U0 + 1/2) with u = fx x + s y + cx, j + 1/2 = k (v - V0 + 1/2), v = fy y + cy
        fx, sk, cx, fy, cy = L.K[0, 0], L.K[0, 1], L.K[0, 2], L.K[1, 1], L.K[1, 2]
        A = np.zeros((3, 3))
        A[0] = [k * fx * 2 * tan_x / Wt, k * sk * 2 * tan_y / Wt,
                k * (-fx * tan_x - sk * tan_y + cx - U0 + 0.5) / Wt]
        A[1] = [0.0, k * fy * 2 * tan_y / Ht, k * (-fy * tan_y + cy - V0 + 0.5) / Ht]
        A[2, 2] = 1.0
        self._to_uv = A
        # a Gaussian for the defocus (sigma in fine texels), or none
        self._blur = s.defocus_px * k
        self._lut = ((np.arange(256) / 255.0) ** L.gamma).astype(np.float32)

    def texture(self, frame: np.ndarray) -> np.ndarray:
        """The projector texture of a frame, (H_t, W_t) float32: the light each ideal direction
        carries, ``(value / 255)^gamma_light`` blurred by the defocus (see the module docstring)."""
        import cv2

        f = np.asarray(frame)
        pw, ph = self.projector_size
        if f.shape != (ph, pw):
            raise ValueError(f"frame: expected shape ({ph}, {pw}) (the projector's), got {f.shape}")
        if f.dtype != np.uint8:
            raise ValueError(f"frame: expected uint8, got {f.dtype}")
        k, pad = self._k, self._pad
        e = self._lut[f]
        if k > 1:
            e = np.repeat(np.repeat(e, k, 0), k, 1)
        fine = np.zeros((self._fine[1], self._fine[0]), np.float32)
        fine[pad:pad + ph * k, pad:pad + pw * k] = e
        if self._blur > 0:
            fine = cv2.GaussianBlur(fine, (0, 0), self._blur, borderType=cv2.BORDER_CONSTANT)
        if self._tex_map is None:
            return fine
        return cv2.remap(fine, self._tex_map[0], self._tex_map[1], cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT,
                         borderValue=0.0)

    # -- the Mitsuba scene of a view

    def _scene_dict(self, *, emitter: dict, spp: int) -> dict:
        mi = self._mi
        L = self._light
        c = self.rig.camera
        Rm = np.asarray(c.R, float) @ L.R.T              # M -> camera
        C = L.R @ c.center + L.t                         # camera centre in M
        cam = np.eye(4)
        cam[:3, :3] = Rm.T @ _FLIP
        cam[:3, 3] = C
        Wc, Hc = self._canvas
        d = {"type": "scene",
             "integrator": {"type": "path", "max_depth": int(self.mitsuba.max_depth), "hide_emitters": True},
             "sensor": {"type": "perspective", "fov": self._fov, "fov_axis": "x",
                        "principal_point_offset_x": self._ppo[0], "principal_point_offset_y": self._ppo[1],
                        "near_clip": 1e-2, "far_clip": 1e7,
                        "to_world": mi.ScalarTransform4f(cam),
                        "film": {"type": "hdrfilm", "width": Wc, "height": Hc, "pixel_format": "luminance",
                                 "rfilter": {"type": "box"}, "sample_border": False},
                        "sampler": {"type": "independent", "sample_count": int(spp)}},
             "light": emitter}
        for i, mesh in enumerate(self._meshes()):
            d[f"mesh_{i}"] = mesh
        return d

    def _meshes(self) -> list:
        """The object (one Mitsuba mesh per albedo) and the reference plane, in the frame M."""
        L = self._light
        s = self.settings
        out = []
        V = self.object_vertices() @ L.R.T + L.t
        F = np.asarray(self.scene.faces, np.int64)
        groups = [(s.albedo, np.arange(len(F)))]
        if self.scene.face_albedo is not None:
            fa = np.asarray(self.scene.face_albedo, float)
            groups = [(float(a), np.nonzero(fa == a)[0]) for a in np.unique(fa)]
        for a, idx in groups:
            if len(idx) == 0:
                continue
            used, inv = np.unique(F[idx].ravel(), return_inverse=True)
            out.append(self._mesh(f"object_{len(out)}", V[used], inv.reshape(-1, 3), a,
                                  coat_roughness=self.mitsuba.coat_roughness))
        # the reference plane z = 0: a central square and four trapezoids around it
        a, b = _PLANE_INNER_MM, PLANE_HALF_MM
        P = np.array([[-a, -a], [a, -a], [a, a], [-a, a], [-b, -b], [b, -b], [b, b], [-b, b]], float)
        P = np.concatenate([P, np.zeros((8, 1))], 1) @ L.R.T + L.t
        Fp = np.array([[0, 1, 2], [0, 2, 3], [4, 5, 1], [4, 1, 0], [5, 6, 2], [5, 2, 1], [6, 7, 3], [6, 3, 2],
                       [7, 4, 0], [7, 0, 3]])
        out.append(self._mesh("plane", P, Fp, s.albedo))
        return out

    def _mesh(self, name: str, V: np.ndarray, F: np.ndarray, albedo: float, *, coat_roughness: float | None = None):
        mi = self._mi
        props = mi.Properties()
        rgb = {"type": "rgb", "value": [float(albedo)] * 3}
        if coat_roughness is None:
            bsdf = {"type": "diffuse", "reflectance": rgb}
        else:
            bsdf = {"type": "roughplastic", "distribution": "ggx", "alpha": float(coat_roughness),
                    "int_ior": COAT_IOR, "diffuse_reflectance": rgb}
        props["bsdf"] = mi.load_dict({"type": "twosided", "bsdf": bsdf})
        m = mi.Mesh(name, len(V), len(F), props=props, has_vertex_normals=False, has_vertex_texcoords=False)
        p = mi.traverse(m)
        p["vertex_positions"] = type(p["vertex_positions"])(np.ascontiguousarray(V, np.float32).ravel())
        p["faces"] = type(p["faces"])(np.ascontiguousarray(F, np.uint32).ravel())
        p.update()
        return m

    def _build_view(self) -> dict:
        if self._view is not None:
            return self._view
        mi = self._mi
        t0 = time.perf_counter()
        L = self._light
        Wt, Ht = self._tex
        # full white at the depth of the scene's centre gives irradiance 1 (ringscan's full white)
        V = self.object_vertices()
        centre = 0.5 * (V.min(0) + V.max(0)) if len(V) else np.zeros(3)
        z_ref = float((L.R @ centre + L.t - L.position) @ (L.to_world[:3, :3] @ np.array([0.0, 0.0, 1.0])))
        if not z_ref > 0:
            raise ValueError("rig: the scene's centre lies behind the projector")
        bitmap = mi.Bitmap(np.zeros((Ht, Wt, 1), np.float32))
        emitter = {"type": "projector", "fov": self._proj_fov, "fov_axis": "x", "scale": z_ref ** 2,
                   "to_world": mi.ScalarTransform4f(L.to_world),
                   "irradiance": {"type": "bitmap", "bitmap": bitmap, "raw": True, "wrap_mode": "clamp",
                                  "filter_type": "bilinear" if self._k > 1 else "nearest",
                                  "to_uv": mi.ScalarTransform3f(self._to_uv)}}
        scene = mi.load_dict(self._scene_dict(emitter=emitter, spp=self.mitsuba.spp))
        params = mi.traverse(scene)
        key = next(k for k in params.keys() if k.endswith("irradiance.data"))
        ambient = None
        if self.settings.ambient > 0:
            amb = mi.load_dict(self._scene_dict(emitter={"type": "constant", "radiance": {
                "type": "rgb", "value": [float(self.settings.ambient)] * 3}}, spp=self.mitsuba.ambient_spp))
            seed = _seed(self.settings.seed, int(round(self._deg * 1000)), 0xA3B1)
            ambient = self._to_pixels(np.asarray(mi.render(amb, seed=seed & 0xFFFFFFFF))[..., 0])
        self._view = {"scene": scene, "params": params, "key": key, "ambient": ambient, "truth": None}
        log.info("Mitsuba (%s): %s at %.1f deg: scene and ambient image (%dx%d canvas, %d spp) in %.2f s",
                 self.variant, self.scene.name, self._deg, self._canvas[0], self._canvas[1],
                 self.mitsuba.ambient_spp, time.perf_counter() - t0)
        return self._view

    def _to_pixels(self, canvas: np.ndarray) -> np.ndarray:
        """Camera pixels from the canvas: the mean of each pixel's S x S sub-samples."""
        import cv2

        c = self.rig.camera
        S = self.settings.supersample
        sub = cv2.remap(np.ascontiguousarray(canvas, np.float32), self._map_x, self._map_y, cv2.INTER_LINEAR,
                        borderMode=cv2.BORDER_REPLICATE)
        return sub.reshape(c.height, S, c.width, S).mean(axis=(1, 3), dtype=np.float64)

    # -- rendering

    def render_linear(self, frame: np.ndarray, *, seed: int = 0) -> np.ndarray:
        """(H, W) float64 radiance at the camera under a frame (ambient included), before the
        camera's response: 1 is full white on an albedo-1 surface facing the light."""
        mi = self._mi
        v = self._build_view()
        tex = self.texture(frame)
        v["params"][v["key"]] = mi.TensorXf(tex[..., None])
        v["params"].update()
        img = np.asarray(mi.render(v["scene"], seed=int(seed) & 0xFFFFFFFF))[..., 0]
        out = self._to_pixels(img)
        if v["ambient"] is not None:
            out = out + v["ambient"]
        return out

    def render(self, frame: np.ndarray, *, seed: int | None = None) -> np.ndarray:
        """The camera image under a projector frame, as :meth:`VirtualRig.render` records it.

        Args:
            frame: (H_p, W_p) uint8 projector frame.
            seed: seed of the path tracer and the camera noise; None derives one from
                ``settings.seed`` and a call counter.

        Returns:
            (H, W) uint8 (8-bit) or uint16 (16-bit) image.
        """
        if seed is None:
            seed = _seed(self.settings.seed, self._calls, 0x5EED)
            self._calls += 1
        elif isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
            raise ValueError(f"seed: expected a non-negative integer, got {seed!r}")
        s = self.settings
        radiance = self.render_linear(frame, seed=_seed(int(seed), 1))
        gamma = float(self.rig.camera.gamma)
        full = (1.0 + s.ambient) / s.exposure ** gamma
        rec = s.full_scale * np.clip(radiance / full, 0.0, None) ** (1.0 / gamma)
        if s.noise > 0:
            rng = np.random.default_rng(_seed(int(seed), 2))
            rec = rec + rng.normal(0.0, s.noise * s.full_scale / 255.0, rec.shape)
        img = np.clip(np.rint(rec), 0, s.full_scale)
        return img.astype(np.uint8 if s.bit_depth == 8 else np.uint16)

    # -- truth

    def truth(self) -> dict:
        """Ground truth of the current view, from Mitsuba's own ray intersections.

        Returns:
            ``depth`` (H, W) float32 camera Z_c (mm, NaN = no hit), ``lit`` (H, W) bool,
            ``points`` (H, W, 3) float32 world points (NaN = no hit).
        """
        v = self._build_view()
        if v["truth"] is None:
            t0 = time.perf_counter()
            v["truth"] = self._trace_truth(v["scene"])
            log.info("Mitsuba (%s): truth of %s at %.1f deg in %.2f s", self.variant, self.scene.name, self._deg,
                     time.perf_counter() - t0)
        return {k: a.copy() for k, a in v["truth"].items()}

    def _trace_truth(self, scene) -> dict:
        mi = self._mi
        L = self._light
        c = self.rig.camera
        H, W = c.height, c.width
        Rm = np.asarray(c.R, float) @ L.R.T
        C = L.R @ c.center + L.t
        dc = np.concatenate([self._centre_xy, np.ones((len(self._centre_xy), 1))], 1)
        dc /= np.linalg.norm(dc, axis=1, keepdims=True)
        dM = dc @ Rm                                       # rows: Rm^T dc
        n = len(dM)
        if self.variant == "scalar_rgb":
            t, P, N, shadow = _truth_scalar(mi, scene, C, dM, L.position)
        else:
            t, P, N, shadow = _truth_vector(mi, scene, C, dM, L.position)
        hit = np.isfinite(t)
        depth = np.where(hit, t * dc[:, 2], np.nan)
        # facet normal turned toward the camera; lit where the light is on the same side
        N = np.where((np.sum(N * dM, 1) > 0)[:, None], -N, N)
        to_light = L.position[None, :] - P
        facing = np.sum(N * to_light, 1) > 0
        inside = np.zeros(n, bool)
        Pw = (P - L.t) @ L.R                               # world points (rows: R^T (P - t))
        if L.parallel is not None:
            li = L.parallel
            XL = P  # M is the light frame
            u = XL[:, 0] / li.pixel_pitch_mm + li.axis_px[0]
            vv = XL[:, 1] / li.pixel_pitch_mm + li.axis_px[1]
            ok = hit
        else:
            ok = hit & (P[:, 2] > 0)
            u = np.full(n, np.nan)
            vv = np.full(n, np.nan)
            if ok.any():
                xy = P[ok, :2] / P[ok, 2:3]
                # distortion polynomials fold back far outside the image: only project what lies
                # within twice the image's half-diagonal of the principal ray
                K = L.K
                lim = 2.0 * math.hypot(L.size[0], L.size[1]) / min(abs(K[0, 0]), abs(K[1, 1]))
                near = np.hypot(xy[:, 0], xy[:, 1]) < lim
                uv = np.full((len(xy), 2), np.nan)
                if near.any():
                    uv[near] = _pixels_from_normalized(K, L.dist, xy[near])
                u[ok], vv[ok] = uv[:, 0], uv[:, 1]
        pw, ph = L.size
        with np.errstate(invalid="ignore"):
            inside = ok & (u >= -0.5) & (u <= pw - 0.5) & (vv >= -0.5) & (vv <= ph - 0.5)
        lit = hit & facing & ~shadow & inside
        pts = np.where(hit[:, None], Pw, np.nan)
        return {"depth": depth.reshape(H, W).astype(np.float32), "lit": lit.reshape(H, W),
                "points": pts.reshape(H, W, 3).astype(np.float32)}


def _truth_vector(mi, scene, C, dM, light_pos):
    """Intersections and shadow rays of all centre rays at once (a vectorised variant)."""
    n = len(dM)
    o = mi.Point3f(*(np.full(n, C[i], np.float32) for i in range(3)))
    d = mi.Vector3f(*(np.ascontiguousarray(dM[:, i], np.float32) for i in range(3)))
    si = scene.ray_intersect(mi.Ray3f(o, d))
    valid = np.asarray(si.is_valid(), bool)
    t = np.where(valid, np.asarray(si.t, np.float64), np.inf)
    P = np.stack([np.asarray(si.p[i], np.float64) for i in range(3)], -1)
    N = np.stack([np.asarray(si.n[i], np.float64) for i in range(3)], -1)
    target = mi.Point3f(*(np.full(n, light_pos[i], np.float32) for i in range(3)))
    occluded = np.asarray(scene.ray_test(si.spawn_ray_to(target), si.is_valid()), bool)
    P = np.where(valid[:, None], P, np.nan)
    N = np.where(valid[:, None], N, np.nan)
    t = np.where(valid, t, np.nan)
    return t, P, N, occluded & valid


def _truth_scalar(mi, scene, C, dM, light_pos):
    """As :func:`_truth_vector`, one ray at a time (the scalar variant)."""
    n = len(dM)
    t = np.full(n, np.nan)
    P = np.full((n, 3), np.nan)
    N = np.full((n, 3), np.nan)
    occ = np.zeros(n, bool)
    o = mi.Point3f(*(float(x) for x in C))
    target = mi.Point3f(*(float(x) for x in light_pos))
    for i in range(n):
        si = scene.ray_intersect(mi.Ray3f(o, mi.Vector3f(float(dM[i, 0]), float(dM[i, 1]), float(dM[i, 2]))))
        if not si.is_valid():
            continue
        t[i] = si.t
        P[i] = (si.p[0], si.p[1], si.p[2])
        N[i] = (si.n[0], si.n[1], si.n[2])
        occ[i] = bool(scene.ray_test(si.spawn_ray_to(target)))
    return t, P, N, occ


def _seed(*parts: int) -> int:
    return int(np.random.SeedSequence([int(p) & 0xFFFFFFFFFFFF for p in parts]).generate_state(1)[0]) & 0x7FFFFFFF
