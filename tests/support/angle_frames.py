"""The angle code's frames drawn from its own formula, as a camera that sees the projector's grid one to one
would record them (known truth at every sub-pixel position), and their decode, for the angle kernel's tests
(tests/kernels/test_angle.py, test_launch.py)."""

import numpy as np
import warp as wp

from ringscan.kernels.angle import decode_angle
from ringscan.kernels.settings import AngleSettings
from ringscan.pipeline.formats.patterns import angle_periods

C = (200.3, 150.7)
SB = 6
STEPS = 4
RHO0, PITCH, BANDS = 8.0, 4.0, 48


def angle_frames(gamma_cam=1.0, noise=0.0, seed=0, contrast=200.0, zones=None):
    """White, black and the angle steps' frames (400x300, 8 bits) drawn from the code's formula for ``zones``;
    each pixel's radius and polar angle."""
    h, w = 300, 400
    y, x = np.mgrid[0:h, 0:w].astype(np.float64)
    rho = np.hypot(x - C[0], y - C[1])
    phi = np.arctan2(y - C[1], x - C[0])
    starts, periods = zones
    P = angle_periods(rho, starts, periods)
    lit = (rho >= RHO0) & (rho < RHO0 + BANDS * PITCH)
    irr = [np.ones_like(rho), np.zeros_like(rho)]
    irr += [np.where(lit, 0.5 + 0.5 * np.cos(P * phi - 2 * np.pi * n / STEPS), 0.0) for n in range(STEPS)]
    rng = np.random.default_rng(seed)
    out = []
    for f in irr:
        level = 20.0 + contrast * f ** (1.0 / gamma_cam) if gamma_cam != 1.0 else 20.0 + contrast * f
        out.append(np.clip(np.round(level + rng.normal(0, noise, level.shape)), 0, 255).astype(np.uint8))
    return np.stack(out), rho, phi


def angle_lut(gamma_cam, contrast=200.0):
    """The camera's response table of :func:`angle_frames`' levels."""
    # recorded = 20 + contrast * irradiance^(1/g): invert it
    r = np.arange(256, dtype=np.float64)
    lin = np.clip((r - 20.0) / contrast, 0, None) ** gamma_cam
    return lin.astype(np.float32)


def angle_decode(device, frames, pts, rho, sector, zones, lut, settings=AngleSettings()):
    """decode_angle of the samples ``pts`` (their radius and sector given) in ``frames`` on ``device``."""
    return decode_angle(wp.array(frames, device=device), wp.array(pts.astype(np.float32), dtype=wp.vec2, device=device),
                        wp.array(rho.astype(np.float32), device=device), wp.array(sector.astype(np.int32), device=device),
                        white=0, black=1, angle0=2, steps=STEPS, sector_bits=SB, zones=zones,
                        lut=wp.array(lut, device=device), settings=settings)


def angle_samples(n=3000, seed=1):
    """Seeded sub-pixel positions in the lit annulus: (points, radius, polar angle, sector)."""
    rng = np.random.default_rng(seed)
    r = rng.uniform(RHO0 + 2, RHO0 + BANDS * PITCH - 2, n)
    a = rng.uniform(-np.pi, np.pi, n)
    pts = np.c_[C[0] + r * np.cos(a), C[1] + r * np.sin(a)]
    ok = (pts[:, 0] > 1) & (pts[:, 0] < 398) & (pts[:, 1] > 1) & (pts[:, 1] < 298)
    pts, r, a = pts[ok], r[ok], a[ok]
    sector = np.floor((a + np.pi) / (2 * np.pi) * 2 ** SB).astype(np.int32)
    return pts, r, a, sector
