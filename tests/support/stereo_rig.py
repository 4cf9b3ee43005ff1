"""The hand-made two-camera rig of test_stereo_match and test_stereo_rays: two cameras and a
projector around a known sphere (or a step); truth projected through each lens gives the exact
projector coordinates and pixels."""

import cv2
import numpy as np
import warp as wp

from ringscan.pipeline.formats.rig import Camera, look_at

PW, PH = 1024, 768
CENTER = (511.5, 383.5)
VOLUME = (-10.0, 95.0, 100.0)
SPHERE_C = np.array([0.0, 0.0, -40.0])
SPHERE_R = 70.0  # cap reaching z = 30 at the centre


def _cam(eye, dist=(0.02, -0.05, 0.001, -0.0005, 0.0)):
    R, t = look_at(eye, [0.0, 0.0, 20.0])
    K = np.array([[2600.0, 0, 639.5], [0, 2600.0, 511.5], [0, 0, 1.0]])
    return Camera(width=1280, height=1024, K=K, dist=np.asarray(dist, float), R=R, t=t)


CAM1 = _cam([0.0, -240.0, 370.0])
CAM2 = _cam([0.0, 240.0, 370.0], dist=(-0.03, 0.04, -0.0008, 0.0006, 0.0))
_Rp, _tp = look_at([0.0, 0.0, 600.0], [0.0, 0.0, 0.0])
PROJ = Camera(width=PW, height=PH, K=np.array([[575 / 0.15, 0, 511.5], [0, 575 / 0.15, 383.5], [0, 0, 1.0]]),
              dist=np.array([0.03, -0.01, 0.0, 0.0, 0.0]), R=_Rp, t=_tp)


def project_points(c, X):
    """OpenCV's pixels of world points X in camera (or projector) c."""
    return cv2.projectPoints(np.asarray(X, float), cv2.Rodrigues(c.R)[0], c.t, c.K, c.dist)[0][:, 0]


def _rays(c, uv):
    n = cv2.undistortPoints(np.asarray(uv, float).reshape(-1, 1, 2), c.K, c.dist,
                            criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-12))[:, 0]
    d = np.c_[n, np.ones(len(n))] @ c.R  # R^T (x, y, 1)
    return c.center, d / np.linalg.norm(d, axis=1, keepdims=True)


def surface_hits(c, uv, surface="sphere"):
    """World points where the rays of pixels uv meet the surface (NaN: miss)."""
    C, d = _rays(c, uv)
    if surface == "sphere":
        w = C - SPHERE_C
        b = d @ w
        disc = b * b - (w @ w - SPHERE_R ** 2)
        t = -b - np.sqrt(np.where(disc >= 0, disc, np.nan))
    else:  # a step: z = 30 for x < 0, z = 0 for x >= 0 (the wall hidden from nobody that matters here)
        t_hi = (30.0 - C[2]) / d[:, 2]
        t_lo = (0.0 - C[2]) / d[:, 2]
        x_hi = C[0] + t_hi * d[:, 0]
        t = np.where(x_hi < 0, t_hi, t_lo)
        x_lo = C[0] + t_lo * d[:, 0]
        t = np.where((x_hi >= 0) & (x_lo < 0), np.nan, t)  # the step's wall: no sample
    return C + t[:, None] * d


def _visible(c, X, surface="sphere"):
    """X is the first surface point along c's ray through its pixel."""
    back = surface_hits(c, project_points(c, X), surface)
    return np.linalg.norm(back - X, axis=1) < 1e-3


def ring_samples(rng, radii, step=1.0, jitter=0.3):
    """Projector points along rings (tangential spacing ~step px)."""
    ps = []
    for r in radii:
        n = int(2 * np.pi * r / step)
        phi = np.linspace(-np.pi, np.pi, n, endpoint=False) + rng.uniform(-jitter, jitter, n) * step / r
        ps.append(np.c_[CENTER[0] + r * np.cos(phi), CENTER[1] + r * np.sin(phi)])
    return np.concatenate(ps)


def from_projector(p, surface="sphere"):
    """World points of projector points p on the surface, and whether both cameras see each."""
    X = surface_hits(PROJ, p, surface)
    ok = np.isfinite(X).all(axis=1)
    ok[ok] &= _visible(CAM1, X[ok], surface) & _visible(CAM2, X[ok], surface)
    return X, ok


def warp_array(a, dtype, device):
    """``a`` as a float32 warp array of ``dtype`` on ``device``."""
    return wp.array(np.ascontiguousarray(a, dtype=np.float32), dtype=dtype, device=device)
