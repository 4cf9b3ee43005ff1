"""Triangulation, per point: a camera ray meets the quadric of its ring (DESIGN §3, §4).

Both light models give a quadric in the undistorted case:

- parallel: in the light frame, (x_L - e_u)^2 + (y_L - e_v)^2 = (s rho)^2 with
  e = s (c - a): a cylinder around the ring's axis;
- perspective: with X_p the point in the projector frame,
  (fx X_p + skew Y_p + (cx - c_u) Z_p)^2 + (fy Y_p + (cy - c_v) Z_p)^2 = rho^2 Z_p^2:
  the elliptic cone of rays whose undistorted pixel lies on |p - c| = rho.
  With projector distortion each root is refined by Newton steps on
  |pixel(X(t)) - c| - rho, starting from the undistorted cone.

Along the ray X(t) = C + t d both reduce to a (t^2) + b t + c = 0, solved in
float64 with the stable form. Root choice follows DESIGN §4: a root is kept only
in front of the camera and inside the working volume; where both are inside, the
decoded angular sector picks the root whose polar angle (around the pattern
centre, on the projector grid) lies in that sector; without a sector code the
point is dropped and counted as ambiguous, never guessed. With a sector code a
root whose polar angle misses its sector by more than ``sector_tolerance``
sectors is dropped as inconsistent.

Status codes (``status`` array): 0 point, 1 no real root, 2 no root in the
volume, 3 ambiguous (two roots, no way to choose), 4 sector mismatch, 5 grazing
(the ray meets the quadric at a glancing angle: a tiny sampling error moves the
point far along the ray), 6 isolated (set later by ``point_filter``), 7 not
converged (with projector distortion, the Newton refinement of a root in front
of the projector did not reach the ring: where that root lies is unknown, so
neither root can be trusted to be the only one), 8 undistort failed (the
camera pixel has no undistorted point inside the region where the camera's
distortion is monotonic: its ray is unknown).
"""

from __future__ import annotations

from dataclasses import dataclass

import warp as wp

from ringscan.kernels.geometry import (
    LIGHT_PARALLEL,
    CameraModel,
    LightModel,
    Volume,
    camera_ray,
    make_volume,
    pattern_offset,
    polar_angle,
    ray_ring_roots,
    root_usable,
)
from ringscan.kernels.launch import default_threads, launch_spans, scan_counts

STATUS_OK = wp.constant(0)
STATUS_NO_ROOT = wp.constant(1)
STATUS_OUTSIDE = wp.constant(2)
STATUS_AMBIGUOUS = wp.constant(3)
STATUS_SECTOR_MISMATCH = wp.constant(4)
STATUS_GRAZING = wp.constant(5)
STATUS_ISOLATED = 6  # given by kernels.point_filter
STATUS_NOT_CONVERGED = wp.constant(7)
STATUS_UNDISTORT_FAILED = wp.constant(8)
STATUS_NAMES = ("ok", "no_root", "outside_volume", "ambiguous", "sector_mismatch", "grazing", "isolated",
                "not_converged", "undistort_failed")
PI = wp.constant(3.14159265358979)

__all__ = ["TriangulateSettings", "Triangulation", "triangulate_rings", "compact_points", "STATUS_NAMES"]


@dataclass(frozen=True)
class TriangulateSettings:
    """Root choice and consistency settings."""

    sector_tolerance: float = 0.75
    """How far (in sector widths) a root's polar angle may lie outside its decoded
    sector and still count as matching it: it absorbs the half-sector a sample on
    a sector edge may be off. Above it the point is dropped (sector mismatch)."""
    sector_margin: float = 0.5
    """Where both roots lie in the volume, the one nearer the decoded sector wins
    only if the other is farther by at least this many sector widths; otherwise
    the point is dropped as ambiguous."""
    min_incidence_cos: float = 0.03
    """Least |cos| of the angle between the camera ray and the quadric's normal.
    The depth error is the sampling error divided by it: below 0.03 (rays within
    ~2 degrees of grazing the ring's surface) a 0.05 px error costs millimetres."""


@dataclass
class Triangulation:
    """Per-sample triangulation results (Warp arrays of length n)."""

    points: wp.array
    """vec3 world point (mm); zero where status != 0."""
    status: wp.array
    """int32 status code (0 = point)."""
    confidence: wp.array
    """float32 sample confidence times |cos| of the ray's incidence on the quadric."""
    residual: wp.array
    """float32 angular residual in sectors (0 inside the sector; -1 without sectors)."""


# ----------------------------------------------------------------------------- helpers


@wp.func
def sector_residual(light: LightModel, X: wp.vec3, center: wp.vec2, sector: int, n_sectors: int):
    """Distance (in sector widths) of X's polar angle outside decoded ``sector``."""
    off = pattern_offset(light, X, center)
    phi = polar_angle(off[1], off[0])
    width = 2.0 * PI / float(n_sectors)
    mid = (float(sector) + 0.5) * width - PI
    dphi = phi - mid
    dphi = dphi - 2.0 * PI * wp.floor((dphi + PI) / (2.0 * PI))
    return wp.max(wp.abs(dphi) / width - 0.5, 0.0)


# ----------------------------------------------------------------------------- kernels


@wp.kernel
def triangulate_kernel(
    uv: wp.array(dtype=wp.vec2),
    rho: wp.array(dtype=wp.float32),
    sector: wp.array(dtype=wp.int32),
    sample_conf: wp.array(dtype=wp.float32),
    cam: CameraModel,
    light: LightModel,
    vol: Volume,
    center: wp.vec2,
    n_sectors: int,
    sector_tolerance: float,
    sector_margin: float,
    min_incidence_cos: float,
    i0: int,
    points: wp.array(dtype=wp.vec3),
    status: wp.array(dtype=wp.int32),
    confidence: wp.array(dtype=wp.float32),
    residual: wp.array(dtype=wp.float32),
):
    """Triangulate sample i0 + tid.

    uv (n,) vec2, rho (n,) float32 projector px, sector (n,) int32 (-1 unknown),
    sample_conf (n,) float32: read.
    points (n,) vec3, status (n,) int32, confidence (n,) float32,
    residual (n,) float32: written.
    """
    i = i0 + wp.tid()
    d, ray_ok = camera_ray(cam, uv[i][0], uv[i][1])
    C = cam.center
    r = rho[i]
    points[i] = wp.vec3(0.0, 0.0, 0.0)
    confidence[i] = 0.0
    residual[i] = -1.0
    if not ray_ok:
        status[i] = STATUS_UNDISTORT_FAILED
        return
    roots, failed = ray_ring_roots(light, C, d, r, center)
    if roots[2] == 0.0:
        status[i] = STATUS_NO_ROOT
        return
    if failed != 0:
        status[i] = STATUS_NOT_CONVERGED
        return
    t1 = roots[0]
    t2 = roots[1]
    X1 = C + d * t1
    X2 = C + d * t2
    ok1 = root_usable(light, X1, t1, vol)
    ok2 = root_usable(light, X2, t2, vol)
    if not ok1 and not ok2:
        status[i] = STATUS_OUTSIDE
        return
    s = sector[i]
    use_sector = n_sectors > 0 and s >= 0
    X = X1
    res = float(-1.0)
    if use_sector:
        e1 = wp.where(ok1, sector_residual(light, X1, center, s, n_sectors), 1.0e9)
        e2 = wp.where(ok2, sector_residual(light, X2, center, s, n_sectors), 1.0e9)
        if ok1 and ok2 and wp.abs(e1 - e2) < sector_margin:
            status[i] = STATUS_AMBIGUOUS
            return
        if e2 < e1:
            X = X2
            res = e2
        else:
            res = e1
        if res > sector_tolerance:
            status[i] = STATUS_SECTOR_MISMATCH
            residual[i] = res
            return
    else:
        if ok1 and ok2:
            status[i] = STATUS_AMBIGUOUS
            return
        if ok2:
            X = X2
    # Incidence: the angle between the ray and the quadric's normal (the
    # gradient of |p - c|: analytic for the parallel light, numerical otherwise).
    g = wp.vec3(0.0, 0.0, 0.0)
    if light.model == LIGHT_PARALLEL:
        off = pattern_offset(light, X, center)
        g = wp.transpose(light.R) * wp.vec3(off[0], off[1], 0.0)
    else:
        h = 0.01
        f0 = wp.length(pattern_offset(light, X, center))
        g = wp.vec3(wp.length(pattern_offset(light, X + wp.vec3(h, 0.0, 0.0), center)) - f0,
                    wp.length(pattern_offset(light, X + wp.vec3(0.0, h, 0.0), center)) - f0,
                    wp.length(pattern_offset(light, X + wp.vec3(0.0, 0.0, h), center)) - f0)
    gl = wp.length(g)
    cosi = wp.where(gl > 0.0, wp.abs(wp.dot(g, d)) / gl, 0.0)
    points[i] = X
    confidence[i] = sample_conf[i] * cosi
    status[i] = wp.where(cosi >= min_incidence_cos, STATUS_OK, STATUS_GRAZING)
    residual[i] = res


@wp.kernel
def count_valid_kernel(status: wp.array(dtype=wp.int32), flags: wp.array(dtype=wp.int32)):
    """flags[i] = 1 where status[i] == 0. status (n,) read; flags (n,) written."""
    i = wp.tid()
    flags[i] = wp.where(status[i] == STATUS_OK, 1, 0)


@wp.kernel
def compact_kernel(
    status: wp.array(dtype=wp.int32),
    offsets: wp.array(dtype=wp.int32),
    index: wp.array(dtype=wp.int32),
):
    """index[offsets[i]] = i for every valid sample. status, offsets (n,) read;
    index (n_valid,) written."""
    i = wp.tid()
    if status[i] == STATUS_OK:
        index[offsets[i]] = i


# ----------------------------------------------------------------------------- host


def triangulate_rings(
    uv: wp.array,
    rho: wp.array,
    sector: wp.array,
    sample_confidence: wp.array,
    *,
    camera: CameraModel,
    light: LightModel,
    volume: tuple[float, float, float],
    center: tuple[float, float],
    sector_bits: int = 0,
    settings: TriangulateSettings = TriangulateSettings(),
    threads: int | None = None,
) -> Triangulation:
    """Triangulate ring samples: each camera ray meets its ring's quadric.

    Args:
        uv: (n,) vec2 camera pixel coordinates (distorted image).
        rho: (n,) float32 ring radius in projector pixels.
        sector: (n,) int32 decoded sector, -1 where unknown.
        sample_confidence: (n,) float32.
        camera, light: from :mod:`ringscan.kernels.geometry`.
        volume: (z_min, z_max, r_max) of the working volume, world mm.
        center: pattern centre (c_u, c_v) in projector pixels.
        sector_bits: sector Gray-code bits of the scan (0: none).
        settings: root-choice settings.
        threads: CPU threads; default all cores.
    """
    n = uv.shape[0] if isinstance(uv, wp.array) else None
    if n is None or uv.dtype != wp.vec2:
        raise ValueError("triangulate_rings: uv must be a Warp array of vec2")
    for name, a, dt in (("rho", rho, wp.float32), ("sector", sector, wp.int32), ("sample_confidence", sample_confidence, wp.float32)):
        if not isinstance(a, wp.array) or a.dtype != dt or a.shape != (n,):
            raise ValueError(f"triangulate_rings: {name} must be a ({n},) {dt.__name__} Warp array")
    z_min, z_max, r_max = (float(x) for x in volume)
    if not (z_max > z_min and r_max > 0):
        raise ValueError(f"triangulate_rings: bad volume {volume}")
    dev = uv.device
    out = Triangulation(
        points=wp.empty(n, dtype=wp.vec3, device=dev),
        status=wp.empty(n, dtype=wp.int32, device=dev),
        confidence=wp.empty(n, dtype=wp.float32, device=dev),
        residual=wp.empty(n, dtype=wp.float32, device=dev),
    )
    if n == 0:
        return out
    vol = make_volume(z_min, z_max, r_max)
    n_sectors = 2 ** sector_bits if sector_bits > 0 else 0
    args = [uv, rho, sector, sample_confidence, camera, light, vol, wp.vec2(*center), n_sectors,
            settings.sector_tolerance, settings.sector_margin, settings.min_incidence_cos]
    outputs = [out.points, out.status, out.confidence, out.residual]
    threads = default_threads() if threads is None else threads
    launch_spans(triangulate_kernel, n, lambda i0: args + [i0], outputs, dev, threads)
    return out


def compact_points(status: wp.array) -> wp.array:
    """Indices (int32, ascending) of the samples that became points (status 0)."""
    n = status.shape[0]
    dev = status.device
    if n == 0:
        return wp.empty(0, dtype=wp.int32, device=dev)
    flags = wp.empty(n, dtype=wp.int32, device=dev)
    wp.launch(count_valid_kernel, dim=n, inputs=[status], outputs=[flags], device=dev)
    offsets, total = scan_counts(flags)
    index = wp.empty(total, dtype=wp.int32, device=dev)
    if total:
        wp.launch(compact_kernel, dim=n, inputs=[status, offsets], outputs=[index], device=dev)
    return index
