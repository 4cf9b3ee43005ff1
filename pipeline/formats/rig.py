"""The rig (calibration) file: camera, light, working volume and turntable (docs/design.md §11).

A rig file is JSON::

    {"format": "ringscan.rig/1", "units": "mm",
     "camera": {"width": W, "height": H, "K": 3x3, "dist": [k1,k2,p1,p2,k3] (or 4, 8, 12 values),
                "R": 3x3, "t": [3], "response": {"gamma": g}},
     "light": {"model": "parallel", "R": 3x3, "t": [3], "pixel_pitch_mm": s,
               "axis_px": [a_u, a_v]}
           or {"model": "perspective", "width": .., "height": .., "K": .., "dist": ..,
               "R": .., "t": ..}
           or {"model": "uncalibrated", "width": .., "height": ..}   (two-camera rigs only),
     "camera2": {...as camera...}                                    (optional: a second camera),
     "volume": {"z_min": .., "z_max": .., "r_max": ..},
     "turntable": {"axis_point": [3], "axis_dir": [3]}}

Frames (docs/design.md §2): world W has its origin where the light axis meets the reference
plane, z toward the light. The camera follows OpenCV: ``X_c = R X_w + t``. The light
frame L is ``X_L = R_L X_w + t_L``.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass, field

import numpy as np

from ringscan.pipeline.formats.atomic import atomic_write_json, read_json
from ringscan.pipeline.formats.errors import FormatError
from ringscan.pipeline.formats.limits import MAX_IMAGE_PIXELS

RIG_FORMAT = "ringscan.rig/1"

__all__ = ["RIG_FORMAT", "DIST_SIZES", "read_distortion", "Camera", "ParallelLight", "PerspectiveLight", "UncalibratedLight", "Volume", "Turntable", "Rig", "load_rig", "parse_rig", "save_rig", "rig_to_dict", "default_rig", "look_at", "turntable_transform",
           "has_calibrated_light"]


@dataclass(frozen=True)
class Camera:
    """A calibrated OpenCV pinhole camera."""

    width: int
    """Image width in pixels."""
    height: int
    """Image height in pixels."""
    K: np.ndarray
    """3x3 intrinsic matrix [[fx, 0, cx], [0, fy, cy], [0, 0, 1]]."""
    dist: np.ndarray
    """Distortion in OpenCV order: (k1, k2, p1, p2, k3), or 8 (+ k4, k5, k6: the
    rational model) or 12 (+ s1, s2, s3, s4: thin prism) coefficients."""
    R: np.ndarray
    """3x3 rotation world -> camera."""
    t: np.ndarray
    """Translation world -> camera (mm): X_c = R X_w + t."""
    gamma: float = 1.0
    """Response: recorded = full_scale * (irradiance / full)^(1/gamma); 1 = linear."""

    @property
    def center(self) -> np.ndarray:
        """Camera centre in world coordinates (mm)."""
        return -self.R.T @ self.t


@dataclass(frozen=True)
class ParallelLight:
    """The paper's collimated light: projector pixel (u_p, v_p) lights the line
    x_L = s (u_p - a_u), y_L = s (v_p - a_v), travelling toward -z_L."""

    R: np.ndarray
    """3x3 rotation world -> light frame."""
    t: np.ndarray
    """Translation world -> light frame (mm)."""
    pixel_pitch_mm: float
    """s: size of one projector pixel at the object (mm)."""
    axis_px: np.ndarray
    """a = (a_u, a_v): the projector pixel on the light axis."""
    width: int = 0
    """Projector width in pixels (0 = unknown; then the pattern's width is used)."""
    height: int = 0
    """Projector height in pixels (0 = unknown)."""
    gamma: float = 1.0
    """Light response: emitted = (value / full_scale)^gamma; 1 = linear."""
    model: str = field(default="parallel", init=False)


@dataclass(frozen=True)
class PerspectiveLight:
    """A real projector: an inverse OpenCV camera, X_p = R X_w + t."""

    width: int
    """Projector width in pixels."""
    height: int
    """Projector height in pixels."""
    K: np.ndarray
    """3x3 intrinsic matrix."""
    dist: np.ndarray
    """Distortion in OpenCV order: 5, 8 or 12 coefficients (as :attr:`Camera.dist`)."""
    R: np.ndarray
    """3x3 rotation world -> projector."""
    t: np.ndarray
    """Translation world -> projector (mm)."""
    gamma: float = 1.0
    """Light response: emitted = (value / full_scale)^gamma; 1 = linear."""
    model: str = field(default="perspective", init=False)

    @property
    def center(self) -> np.ndarray:
        """Projector centre in world coordinates (mm)."""
        return -self.R.T @ self.t


@dataclass(frozen=True)
class UncalibratedLight:
    """A projector whose geometry is not known: the pattern's size only. Allowed in
    two-camera rigs, which triangulate camera to camera (docs/formats.md)."""

    width: int
    """Projector width in pixels."""
    height: int
    """Projector height in pixels."""
    gamma: float = 1.0
    """Light response: emitted = (value / full_scale)^gamma; 1 = linear."""
    model: str = field(default="uncalibrated", init=False)


@dataclass(frozen=True)
class Volume:
    """The rig's working volume in the world frame; roots outside it are rejected."""

    z_min: float
    """Lowest z (mm); a little below 0 keeps the reference plane."""
    z_max: float
    """Highest z (mm)."""
    r_max: float
    """Largest distance from the light axis (mm)."""


@dataclass(frozen=True)
class Turntable:
    """A turntable: a view at angle theta has the object turned by theta about the axis."""

    axis_point: np.ndarray
    """A point on the axis (world, mm)."""
    axis_dir: np.ndarray
    """Unit direction of the axis (world); rotation is right-handed about it."""


@dataclass(frozen=True)
class Rig:
    """A whole rig: camera, light, working volume, optional turntable and second camera."""

    camera: Camera
    """The camera (camera 1 of a two-camera rig)."""
    light: ParallelLight | PerspectiveLight | UncalibratedLight
    """The light; ``UncalibratedLight`` only when ``camera2`` is present."""
    volume: Volume
    """The working volume (world frame)."""
    turntable: Turntable | None = None
    """The turntable, if any."""
    camera2: Camera | None = None
    """The second camera of a two-camera rig (same world frame), or None."""

    def to_dict(self) -> dict:
        return rig_to_dict(self)


# ----------------------------------------------------------------------------- parsing


# Sane ranges (docs/formats.md "Rig file: ranges"): a value outside them is a
# broken or mistyped file, never a rig that works.
MAX_LENGTH_MM = 1e5
"""Largest |value| of a length (translations, volume, turntable axis point): 100 m."""
MAX_PIXELS = 1e6
"""Largest focal length, |principal point|, |skew| and |axis_px| in pixels."""
MIN_FOCAL_PX = 1.0
"""Smallest focal length in pixels."""
MAX_DISTORTION = 1e3
"""Largest |distortion coefficient|."""
PIXEL_PITCH_RANGE_MM = (1e-4, 100.0)
"""Projector pixel size at the object (parallel light), mm."""
GAMMA_RANGE = (0.1, 10.0)
"""Response gamma."""
MAX_IMAGE_SIZE = 65536
"""Largest camera or projector width / height in pixels."""


def _is_number(v) -> bool:
    return isinstance(v, (int, float, np.integer, np.floating)) and not isinstance(v, (bool, np.bool_))


def _num(src, where, v, lo: float | None = None, hi: float | None = None) -> float:
    if not _is_number(v):
        raise FormatError(src, f"{where}: expected a number, got {v!r}")
    if not math.isfinite(v):
        raise FormatError(src, f"{where}: not finite ({v})")
    if (lo is not None and v < lo) or (hi is not None and v > hi):
        raise FormatError(src, f"{where}: {v:g} is outside the sane range [{lo:g}, {hi:g}]")
    return float(v)


def _leaves(v):
    if isinstance(v, np.ndarray):
        yield from v.ravel().tolist() if v.dtype.kind in "iuf" else [object()]
    elif isinstance(v, (list, tuple)):
        for x in v:
            yield from _leaves(x)
    else:
        yield v


def _arr(src, where, v, shape, max_abs: float | None = None) -> np.ndarray:
    bad = next((x for x in _leaves(v) if not _is_number(x)), None) if v is not None else None
    if v is None or bad is not None:
        got = "nothing" if v is None else f"{bad!r}"
        raise FormatError(src, f"{where}: expected numbers of shape {shape}, got {got}")
    try:
        a = np.asarray(v, dtype=np.float64)
    except (TypeError, ValueError):
        raise FormatError(src, f"{where}: expected numbers of shape {shape}") from None
    if a.shape != shape:
        raise FormatError(src, f"{where}: expected shape {shape}, got {a.shape}")
    if not np.all(np.isfinite(a)):
        raise FormatError(src, f"{where}: contains non-finite values")
    if max_abs is not None and np.abs(a).max(initial=0.0) > max_abs:
        raise FormatError(src, f"{where}: {np.abs(a).max():g} is outside the sane range (|value| <= {max_abs:g})")
    return a


def _rotation(src, where, v) -> np.ndarray:
    R = _arr(src, where, v, (3, 3))
    err = np.abs(R @ R.T - np.eye(3)).max()
    if err > 1e-5 or abs(np.linalg.det(R) - 1.0) > 1e-5:
        raise FormatError(src, f"{where}: not a rotation matrix (|R R^T - I| = {err:.2g}, det = {np.linalg.det(R):.6g})")
    return R


def _intrinsics(src, where, v) -> np.ndarray:
    K = _arr(src, where, v, (3, 3))
    if K[0, 0] <= 0 or K[1, 1] <= 0:
        raise FormatError(src, f"{where}: singular intrinsics (fx, fy must be > 0)")
    if not (MIN_FOCAL_PX <= K[0, 0] <= MAX_PIXELS and MIN_FOCAL_PX <= K[1, 1] <= MAX_PIXELS):
        raise FormatError(src, f"{where}: focal lengths {K[0, 0]:g}, {K[1, 1]:g} px are outside the sane range "
                               f"[{MIN_FOCAL_PX:g}, {MAX_PIXELS:g}]")
    if max(abs(K[0, 1]), abs(K[0, 2]), abs(K[1, 2])) > MAX_PIXELS:
        raise FormatError(src, f"{where}: principal point or skew outside the sane range (|value| <= {MAX_PIXELS:g} px)")
    if abs(np.linalg.det(K)) < 1e-9:
        raise FormatError(src, f"{where}: singular intrinsics (fx, fy must be > 0)")
    if np.abs(K[2] - [0, 0, 1]).max() > 1e-9 or abs(K[1, 0]) > 1e-12:
        raise FormatError(src, f"{where}: last row must be [0, 0, 1] and K[1][0] must be 0")
    return K


DIST_SIZES = (4, 5, 8, 12)
"""Distortion vector lengths read: OpenCV's (k1, k2, p1, p2[, k3]), rational model
(+ k4, k5, k6) and thin-prism model (+ s1, s2, s3, s4); 14 (+ taux, tauy) only
with a zero tilt, kept as 12."""


def read_distortion(v, *, source: str | os.PathLike | None = None, where: str = "dist") -> np.ndarray:
    """OpenCV's distortion vector as a rig keeps it: 4 coefficients become 5 (k3 = 0),
    5, 8 and 12 are kept as given, 14 with a zero tilt (taux = tauy = 0) becomes 12;
    None is no distortion (5 zeros). ``v``: a list or an array of any shape (an
    OpenCV 1xN or Nx1 matrix).

    Raises:
        FormatError: naming ``source`` and ``where``: another count, a non-finite
            value, a nonzero tilt, or a value outside the sane range."""
    if isinstance(v, np.ndarray):
        v = v.ravel().tolist() if v.dtype.kind in "iuf" else [object()]
    return _dist(source, where, v)


def _dist(src, where, v) -> np.ndarray:
    if v is None:
        return np.zeros(5)
    ok = isinstance(v, (list, tuple)) and all(_is_number(x) for x in v)
    a = np.asarray(v, dtype=np.float64).ravel() if ok else None
    if a is None or a.size not in DIST_SIZES + (14,) or not np.all(np.isfinite(a)):
        raise FormatError(src, f"{where}: expected 4, 5, 8 or 12 finite distortion coefficients (OpenCV's order: "
                               "k1, k2, p1, p2[, k3[, k4, k5, k6[, s1, s2, s3, s4]]])")
    if a.size == 14:
        if np.any(a[12:] != 0):
            raise FormatError(src, f"{where}: tilted-sensor model (taux, tauy) not supported "
                                   f"(taux = {a[12]:g}, tauy = {a[13]:g})")
        a = a[:12]
    if np.abs(a).max() > MAX_DISTORTION:
        raise FormatError(src, f"{where}: {np.abs(a).max():g} is outside the sane range (|value| <= {MAX_DISTORTION:g})")
    # 4 coefficients are OpenCV's 5 with k3 = 0; 8 and 12 are kept as given
    return np.concatenate([a, np.zeros(5 - a.size)]) if a.size < 5 else a


def _gamma(src, where, d) -> float:
    resp = d.get("response")
    if resp is None:
        return 1.0
    if not isinstance(resp, dict) or "gamma" not in resp:
        raise FormatError(src, f"{where}.response: expected {{\"gamma\": g}}")
    g = _num(src, f"{where}.response.gamma", resp["gamma"])
    if g <= 0:
        raise FormatError(src, f"{where}.response.gamma: must be > 0")
    return _num(src, f"{where}.response.gamma", g, *GAMMA_RANGE)


def _size(src, where, d, key, required: bool = True) -> int:
    v = d.get(key)
    if v is None and not required:
        return 0
    if isinstance(v, bool) or not isinstance(v, int) or v <= 0:
        raise FormatError(src, f"{where}.{key}: expected a positive integer, got {v!r}")
    if v > MAX_IMAGE_SIZE:
        raise FormatError(src, f"{where}.{key}: {v} px is outside the sane range [1, {MAX_IMAGE_SIZE}]")
    return v


def _check_pixels(src, where: str, width: int, height: int) -> None:
    """Refuse a camera or projector of more pixels than the images ringscan reads: none of its frames could be
    read, and a map of its pixels (conditioning, undistortion) would take gigabytes."""
    if width * height > MAX_IMAGE_PIXELS:
        raise FormatError(src, f"{where}: {width}x{height} is {width * height / 1e6:.0f} megapixels: larger than the "
                               f"images ringscan reads ({MAX_IMAGE_PIXELS / 1e6:.0f} megapixels)")


def _obj(src, where, d, key, required=True):
    v = d.get(key)
    if v is None and not required:
        return None
    if not isinstance(v, dict):
        raise FormatError(src, f"{where}{key}: missing or not an object")
    return v


def parse_rig(d: dict, *, source: str | os.PathLike | None = None) -> Rig:
    """Validate a rig dictionary and build a :class:`Rig`.

    Raises:
        FormatError: naming ``source`` and the field for every problem found.
    """
    src = source
    if not isinstance(d, dict):
        raise FormatError(src, "rig: expected a JSON object")
    fmt = d.get("format")
    if fmt != RIG_FORMAT:
        raise FormatError(src, f"format: unknown rig format {fmt!r} (this version reads {RIG_FORMAT!r})")
    if d.get("units", "mm") != "mm":
        raise FormatError(src, f"units: only 'mm' is supported, got {d.get('units')!r}")

    camera = _camera(src, "camera", _obj(src, "", d, "camera"))
    c2 = _obj(src, "", d, "camera2", required=False)
    camera2 = None if c2 is None else _camera(src, "camera2", c2)

    light = _light(src, _obj(src, "", d, "light"), camera2)
    _check_pixels(src, "light", light.width, light.height)
    volume = _volume(src, _obj(src, "", d, "volume"))
    turntable = _turntable(src, _obj(src, "", d, "turntable", required=False))

    for name, cam in (("camera", camera), ("camera2", camera2)):
        if cam is None:
            continue
        cam_in_front = (cam.R @ np.array([0.0, 0.0, 0.5 * (volume.z_min + volume.z_max)]) + cam.t)[2]
        if cam_in_front <= 0:
            raise FormatError(src, f"{name}: the working volume is behind the camera "
                                   "(check R and t: X_c = R X_w + t)")
    if camera2 is not None and np.linalg.norm(camera.center - camera2.center) < 1e-3:
        raise FormatError(src, "camera2: at the same place as camera (no baseline: check camera2.R and t)")
    return Rig(camera=camera, light=light, volume=volume, turntable=turntable, camera2=camera2)


def _light(src, li: dict, camera2):
    """The rig's ``light`` block: a parallel, perspective or (with a second camera) uncalibrated light."""
    model = li.get("model")
    if model == "parallel":
        s = _num(src, "light.pixel_pitch_mm", li.get("pixel_pitch_mm"))
        if s <= 0:
            raise FormatError(src, "light.pixel_pitch_mm: must be > 0")
        s = _num(src, "light.pixel_pitch_mm", s, *PIXEL_PITCH_RANGE_MM)
        light = ParallelLight(
            R=_rotation(src, "light.R", li.get("R", np.eye(3).tolist())),
            t=_arr(src, "light.t", li.get("t", [0, 0, 0]), (3,), MAX_LENGTH_MM),
            pixel_pitch_mm=s,
            axis_px=_arr(src, "light.axis_px", li.get("axis_px"), (2,), MAX_PIXELS),
            width=_size(src, "light", li, "width", required=False),
            height=_size(src, "light", li, "height", required=False),
            gamma=_gamma(src, "light", li),
        )
    elif model == "perspective":
        light = PerspectiveLight(
            width=_size(src, "light", li, "width"),
            height=_size(src, "light", li, "height"),
            K=_intrinsics(src, "light.K", li.get("K")),
            dist=_dist(src, "light.dist", li.get("dist")),
            R=_rotation(src, "light.R", li.get("R")),
            t=_arr(src, "light.t", li.get("t"), (3,), MAX_LENGTH_MM),
            gamma=_gamma(src, "light", li),
        )
    elif model == "uncalibrated":
        if camera2 is None:
            raise FormatError(src, "light.model: 'uncalibrated' needs a second camera (camera2): a one-camera rig "
                                   "triangulates with the projector, so the projector must be calibrated")
        light = UncalibratedLight(width=_size(src, "light", li, "width"), height=_size(src, "light", li, "height"),
                                  gamma=_gamma(src, "light", li))
    else:
        raise FormatError(src, f"light.model: expected 'parallel', 'perspective' or 'uncalibrated', got {model!r}")
    return light


def _volume(src, v: dict) -> Volume:
    """The rig's ``volume`` block: the working volume, z_min < z_max and r_max > 0."""
    volume = Volume(
        z_min=_num(src, "volume.z_min", v.get("z_min"), -MAX_LENGTH_MM, MAX_LENGTH_MM),
        z_max=_num(src, "volume.z_max", v.get("z_max"), -MAX_LENGTH_MM, MAX_LENGTH_MM),
        r_max=_num(src, "volume.r_max", v.get("r_max"), -MAX_LENGTH_MM, MAX_LENGTH_MM),
    )
    if volume.z_max <= volume.z_min:
        raise FormatError(src, "volume: z_max must be greater than z_min")
    if volume.r_max <= 0:
        raise FormatError(src, "volume.r_max: must be > 0")
    return volume


def _turntable(src, tt: dict | None):
    """The rig's optional ``turntable`` block (None where there is none): its axis, the direction normalised."""
    turntable = None
    if tt is not None:
        ad = _arr(src, "turntable.axis_dir", tt.get("axis_dir"), (3,))
        n = np.linalg.norm(ad)
        if n < 1e-9:
            raise FormatError(src, "turntable.axis_dir: must not be zero")
        turntable = Turntable(axis_point=_arr(src, "turntable.axis_point", tt.get("axis_point"), (3,), MAX_LENGTH_MM),
                              axis_dir=ad / n)
    return turntable


def _camera(src, where: str, c: dict) -> Camera:
    width, height = _size(src, where, c, "width"), _size(src, where, c, "height")
    _check_pixels(src, where, width, height)
    return Camera(
        width=width,
        height=height,
        K=_intrinsics(src, f"{where}.K", c.get("K")),
        dist=_dist(src, f"{where}.dist", c.get("dist")),
        R=_rotation(src, f"{where}.R", c.get("R")),
        t=_arr(src, f"{where}.t", c.get("t"), (3,), MAX_LENGTH_MM),
        gamma=_gamma(src, where, c),
    )


def has_calibrated_light(rig: Rig) -> bool:
    """Whether the rig's projector geometry is known (it can be triangulated with)."""
    return not isinstance(rig.light, UncalibratedLight)


def load_rig(path: str | os.PathLike) -> Rig:
    """Read and validate a rig file."""
    return parse_rig(read_json(path), source=path)


def rig_to_dict(rig: Rig) -> dict:
    """The JSON form of a rig (docs/design.md §11)."""
    li = rig.light
    if isinstance(li, ParallelLight):
        light = {"model": "parallel", "R": li.R.tolist(), "t": li.t.tolist(),
                 "pixel_pitch_mm": li.pixel_pitch_mm, "axis_px": li.axis_px.tolist()}
        if li.width:
            light["width"], light["height"] = li.width, li.height
    elif isinstance(li, UncalibratedLight):
        light = {"model": "uncalibrated", "width": li.width, "height": li.height}
    else:
        light = {"model": "perspective", "width": li.width, "height": li.height, "K": li.K.tolist(),
                 "dist": li.dist.tolist(), "R": li.R.tolist(), "t": li.t.tolist()}
    if li.gamma != 1.0:
        light["response"] = {"gamma": li.gamma}
    d = {"format": RIG_FORMAT, "units": "mm", "camera": _camera_dict(rig.camera), "light": light,
         "volume": {"z_min": rig.volume.z_min, "z_max": rig.volume.z_max, "r_max": rig.volume.r_max}}
    if rig.turntable is not None:
        d["turntable"] = {"axis_point": rig.turntable.axis_point.tolist(), "axis_dir": rig.turntable.axis_dir.tolist()}
    if rig.camera2 is not None:
        d["camera2"] = _camera_dict(rig.camera2)
    return d


def _camera_dict(c: Camera) -> dict:
    cam = {"width": c.width, "height": c.height, "K": c.K.tolist(), "dist": c.dist.tolist(),
           "R": c.R.tolist(), "t": c.t.tolist()}
    if c.gamma != 1.0:
        cam["response"] = {"gamma": c.gamma}
    return cam


def save_rig(path: str | os.PathLike, rig: Rig) -> None:
    """Write a rig file atomically."""
    atomic_write_json(path, rig_to_dict(rig))


def look_at(eye, target, up_hint=(1.0, 0.0, 0.0)) -> tuple[np.ndarray, np.ndarray]:
    """OpenCV extrinsics (R, t) of a camera at ``eye`` looking at ``target``.

    The camera x axis (image u, to the right) is ``up_hint`` made orthogonal to the
    viewing direction; y (image v, down) completes a right-handed frame.
    """
    eye = np.asarray(eye, float)
    z = np.asarray(target, float) - eye
    z /= np.linalg.norm(z)
    x = np.asarray(up_hint, float) - np.dot(up_hint, z) * z
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    R = np.stack([x, y, z])
    return R, -R @ eye


def default_rig(
    *,
    gamma: float = 2.2,
    distance_mm: float = 420.0,
    tilt_deg: float = 35.0,
    focal_px: float = 2600.0,
    dist=(0.02, -0.05, 0.0, 0.0, 0.0),
    light_model: str = "parallel",
    turntable: bool = True,
) -> Rig:
    """The default virtual rig of the issues.

    Camera 1280x1024, f = 2600 px, 420 mm from (0, 0, 25), 35 degrees off the light
    axis on the -y side, distortion k1 = 0.02, k2 = -0.05; parallel light of
    1024x768 projector pixels at 0.15 mm; gamma 2.2; a turntable whose axis is the
    light axis.
    """
    a = math.radians(tilt_deg)
    target = np.array([0.0, 0.0, 25.0])
    eye = target + distance_mm * np.array([0.0, -math.sin(a), math.cos(a)])
    R, t = look_at(eye, target)
    K = np.array([[focal_px, 0, 639.5], [0, focal_px, 511.5], [0, 0, 1.0]])
    cam = Camera(width=1280, height=1024, K=K, dist=np.asarray(dist, float), R=R, t=t, gamma=gamma)
    if light_model == "parallel":
        light = ParallelLight(R=np.eye(3), t=np.zeros(3), pixel_pitch_mm=0.15, axis_px=np.array([511.5, 383.5]),
                              width=1024, height=768)
    elif light_model == "perspective":
        # A projector 600 mm above the plane looking straight down, 1024x768,
        # focal length chosen so that one pixel is ~0.15 mm at z = 25 mm.
        f = 575.0 / 0.15
        Kp = np.array([[f, 0, 511.5], [0, f, 383.5], [0, 0, 1.0]])
        Rp, tp = look_at([0.0, 0.0, 600.0], [0.0, 0.0, 0.0])
        light = PerspectiveLight(width=1024, height=768, K=Kp, dist=np.zeros(5), R=Rp, t=tp)
    else:
        raise ValueError(f"light_model must be 'parallel' or 'perspective', got {light_model!r}")
    vol = Volume(z_min=-3.0, z_max=95.0, r_max=100.0)
    tt = Turntable(axis_point=np.zeros(3), axis_dir=np.array([0.0, 0.0, 1.0])) if turntable else None
    return Rig(camera=cam, light=light, volume=vol, turntable=tt)


def turntable_transform(turntable: Turntable | None, deg: float) -> np.ndarray:
    """4x4 transform that turns the object by ``deg`` about the turntable axis
    (right-handed about ``axis_dir`` through ``axis_point``, docs/design.md §11): it takes
    object-frame points (angle 0) to their world pose in a view at ``deg``; with
    ``-deg`` it brings a view's points back into the object frame. A rig without a
    turntable accepts only multiples of 360 degrees.
    """
    deg = float(deg)
    if not math.isfinite(deg):
        raise ValueError(f"turntable angle must be finite, got {deg}")
    T = np.eye(4)
    if turntable is None:
        if deg % 360.0 != 0.0:
            raise ValueError(f"turntable angle {deg} deg: the rig has no turntable")
        return T
    k = np.asarray(turntable.axis_dir, float)
    k = k / np.linalg.norm(k)
    a = math.radians(deg)
    Kx = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    Rm = np.eye(3) + math.sin(a) * Kx + (1.0 - math.cos(a)) * (Kx @ Kx)
    p = np.asarray(turntable.axis_point, float)
    T[:3, :3] = Rm
    T[:3, 3] = p - Rm @ p
    return T


