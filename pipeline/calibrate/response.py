"""The projector's response curve from camera frames of a projected grey ramp.

The light model of DESIGN §6: emitted = (value / full_scale)^gamma. With the
camera linearised by its own response (``camera_gamma``: recorded =
full * (irradiance / full irradiance)^(1/g)), a pixel's level under a uniform
projected value ``x`` (0..1) is black + (white - black) * x^gamma, so
y = (L(x) - L(0)) / (L(1) - L(0)) = x^gamma and log y = gamma log x. The estimate
is the least-squares slope through the origin over every pixel with contrast and
every level strictly between 0 and 1 (the median per level first, so that a few
saturated or shadowed pixels do not pull it).

Binary Gray-code frames (white, black, pattern, inverse) show only full and no
light and cannot measure this curve: a grey ramp is needed.
"""

from __future__ import annotations

import logging

import numpy as np

from ringscan.pipeline.calibrate.errors import CalibrationError

__all__ = ["estimate_light_gamma"]

log = logging.getLogger(__name__)


def estimate_light_gamma(frames: np.ndarray, levels, *, camera_gamma: float = 1.0, min_contrast: float = 20.0,
                         full_scale: float | None = None) -> tuple[float, dict]:
    """Light gamma from (n, H, W) frames of uniform projected ``levels`` (n values, 0..1, including 0 and 1).

    Returns:
        (gamma, {level: median normalised response}).

    Raises:
        CalibrationError: no level 0 or 1, fewer than two levels between them, or too little contrast.
    """
    fr = np.asarray(frames)
    lv = np.asarray(levels, np.float64).ravel()
    if fr.ndim != 3 or fr.shape[0] != lv.size:
        raise ValueError(f"estimate_light_gamma: frames must be (n, H, W) with n = {lv.size} levels, got {fr.shape}")
    if not (np.any(lv == 0) and np.any(lv == 1)):
        raise CalibrationError(None, "response: the ramp needs a black (0) and a white (1) frame")
    mid = (lv > 0) & (lv < 1)
    if np.count_nonzero(mid) < 2:
        raise CalibrationError(None, "response: need at least two grey levels between black and white")
    full = full_scale or (65535.0 if fr.dtype == np.uint16 else 255.0)
    lin = (fr.astype(np.float64) / full) ** camera_gamma
    black = lin[lv == 0].mean(0)
    white = lin[lv == 1].mean(0)
    ok = (white - black) * full >= min_contrast * (full / 255.0) ** camera_gamma
    ok &= fr[lv == 1].max(0) < 0.99 * full  # unsaturated white
    if np.count_nonzero(ok) < 100:
        raise CalibrationError(None, f"response: only {int(np.count_nonzero(ok))} pixels with contrast (need 100)")
    y = {}
    for x, f in zip(lv[mid], lin[mid]):
        y[float(x)] = float(np.median((f[ok] - black[ok]) / (white[ok] - black[ok])))  # only pixels with contrast
    xs = np.log(np.array(list(y)))
    ys = np.log(np.clip(np.array(list(y.values())), 1e-6, None))
    gamma = float(np.sum(xs * ys) / np.sum(xs * xs))
    if not (0.2 < gamma < 6.0):
        raise CalibrationError(None, f"response: gamma {gamma:.3g} is implausible (levels in the wrong order?)")
    log.info("light gamma %.3f from %d levels over %d pixels", gamma, len(y), int(np.count_nonzero(ok)))
    return gamma, y
