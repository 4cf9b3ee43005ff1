"""A known two-camera + projector rig and exact observations of a non-planar surface (test helper).

The camera and the projector are those of /work/shared/data/rigs/oblique_projector.json
(rounded); camera 2 mirrors camera 1 across the projector's x = 0 plane, so the
two cameras sit ~1.7 m apart, 3.7 m from a surface that spans ~600 mm in depth.
"""

from __future__ import annotations

import cv2
import numpy as np

from ringscan.pipeline.formats.rig import Camera, PerspectiveLight, look_at


def oblique_devices() -> tuple[Camera, Camera, PerspectiveLight]:
    """(camera 1, camera 2, projector) in the world frame of oblique_projector.json."""
    K1 = np.array([[2968.6, 0, 956.5], [0, 2965.9, 754.1], [0, 0, 1.0]])
    d1 = np.array([-0.0119, -1.163, 0.0104, 0.0022, 9.54])
    R1 = np.array([[0.977389973765179, 0.05780371245752069, -0.20339019152710144],
                   [0.03412214995345598, -0.9924185196855726, -0.11807269230288016],
                   [-0.2086732327488521, 0.10846295501794619, -0.9719522978639015]])
    t1 = np.array([-62.59, 541.84, 3821.58])
    cam1 = Camera(width=1920, height=1280, K=K1, dist=d1, R=R1, t=t1)
    c1 = cam1.center
    R2, t2 = look_at([-c1[0], c1[1], c1[2]], [-100.0, 510.0, 300.0], up_hint=(1.0, 0.0, 0.0))
    K2 = np.array([[2900.0, 0, 950.0], [0, 2900.0, 650.0], [0, 0, 1.0]])
    cam2 = Camera(width=1920, height=1280, K=K2, dist=np.array([-0.05, 0.1, 0.0, 0.0, 0.0]), R=R2, t=t2)
    Kp = np.array([[1672.3, 0, 661.5], [0, 1664.9, 758.8], [0, 0, 1.0]])
    proj = PerspectiveLight(width=1280, height=800, K=Kp, dist=np.array([-0.0812, 0.0659, 0.0, 0.0, 0.0]),
                            R=np.diag([1.0, -1.0, -1.0]), t=np.array([0.0, 0.0, 3446.6]))
    return cam1, cam2, proj


def surface_points(n: int, *, seed: int = 0) -> np.ndarray:
    """(n, 3) world points on a wavy surface (z from ~0 to ~600 mm) under the projector."""
    rng = np.random.default_rng(seed)
    x = rng.uniform(-950, 950, n)
    y = rng.uniform(-50, 1300, n)
    z = 300 + 250 * np.sin(x / 230.0) * np.cos(y / 170.0) + 0.03 * (x + 950)
    return np.stack([x, y, z], 1)


def project(dev, X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Exact (distorted) pixels of world points in a device, and whether each is in front and inside its image."""
    Xd = X @ dev.R.T + dev.t
    uv, _ = cv2.projectPoints(Xd.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), dev.K, dev.dist)
    uv = uv.reshape(-1, 2)
    ok = (Xd[:, 2] > 0) & (uv[:, 0] >= 0) & (uv[:, 0] <= dev.width - 1) & (uv[:, 1] >= 0) & (uv[:, 1] <= dev.height - 1)
    return uv, ok


def observe(n: int, *, noise_px: float = 0.1, seed: int = 0):
    """Points seen by all three devices: (X (m, 3), uv1, uv2, uvp with Gaussian noise of ``noise_px``)."""
    cam1, cam2, proj = oblique_devices()
    X = surface_points(n, seed=seed)
    (u1, o1), (u2, o2), (up, op) = project(cam1, X), project(cam2, X), project(proj, X)
    ok = o1 & o2 & op
    rng = np.random.default_rng(seed + 1)
    noisy = [u[ok] + rng.normal(0, noise_px, (int(ok.sum()), 2)) for u in (u1, u2, up)]
    return (X[ok], *noisy)
