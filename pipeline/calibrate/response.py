"""The projector's response curve from camera frames of a projected grey ramp.

The light model of docs/design.md §8: emitted = (value / full_scale)^gamma. With the
camera linearised by its own response (``camera_gamma``: recorded =
full * (irradiance / full irradiance)^(1/g)), a pixel's level under a uniform
projected value ``x`` (0..1) is black + (white - black) * x^gamma, so
y = (L(x) - L(0)) / (L(1) - L(0)) = x^gamma and log y = gamma log x. The estimate
is the least-squares slope through the origin over every pixel with contrast and
every level strictly between 0 and 1 (the median per level first, so that a few
saturated or shadowed pixels do not pull it).

Binary Gray-code frames (white, black, pattern, inverse) show only full and no
light and cannot measure this curve: a grey ramp is needed.

A fit says nothing about frames that do not show the ramp: the same frame given
for three levels yields a flat curve and a plausible-looking gamma (0.91).
:func:`repeated_frames` finds frames given twice for different levels and
:func:`response_problems` a curve that does not rise with the level or does not
follow the power law.
"""

from __future__ import annotations

import logging

import numpy as np

from ringscan.pipeline.calibrate.errors import CalibrationError

__all__ = ["estimate_light_gamma", "repeated_frames", "response_problems"]

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
    if not np.all(np.isfinite(lv) & (lv >= 0) & (lv <= 1)):
        raise ValueError(f"estimate_light_gamma: levels must be finite and in 0..1, got {lv.tolist()}")
    if not (np.any(lv == 0) and np.any(lv == 1)):
        raise CalibrationError(None, "response: the ramp needs a black (0) and a white (1) frame")
    mid = (lv > 0) & (lv < 1)
    if np.count_nonzero(mid) < 2:
        raise CalibrationError(None, "response: need at least two grey levels between black and white")
    full = full_scale or (65535.0 if fr.dtype == np.uint16 else 255.0)
    lin = (fr.astype(np.float64) / full) ** camera_gamma
    black = lin[lv == 0].mean(0)
    white = lin[lv == 1].mean(0)
    ok = (white - black) * full >= min_contrast * (full / 255.0)  # linear levels, 8-bit ones x257 for 16-bit
    ok &= fr[lv == 1].max(0) < 0.99 * full  # unsaturated white
    if np.count_nonzero(ok) < 100:
        raise CalibrationError(None, f"response: only {int(np.count_nonzero(ok))} pixels with contrast (need 100)")
    y = {}
    for x in np.unique(lv[mid]):  # frames of one level are averaged, none is dropped
        f = lin[lv == x].mean(0)
        y[float(x)] = float(np.median((f[ok] - black[ok]) / (white[ok] - black[ok])))  # only pixels with contrast
    xs = np.log(np.array(list(y)))
    ys = np.log(np.clip(np.array(list(y.values())), 1e-6, None))
    gamma = float(np.sum(xs * ys) / np.sum(xs * xs))
    if not (0.2 < gamma < 6.0):
        raise CalibrationError(None, f"response: gamma {gamma:.3g} is implausible (levels in the wrong order?)")
    log.info("light gamma %.3f from %d levels over %d pixels", gamma, len(y), int(np.count_nonzero(ok)))
    return gamma, y


def repeated_frames(frames: np.ndarray, levels) -> list[tuple[int, int]]:
    """Pairs (i, j), i < j, of identical frames given for different levels: the same
    image cannot show two projected values."""
    fr = np.asarray(frames)
    lv = np.asarray(levels, np.float64).ravel()
    out = []
    for j in range(fr.shape[0]):
        for i in range(j):
            if lv[i] != lv[j] and np.array_equal(fr[i], fr[j]):
                out.append((i, j))
                break
    return out


def response_problems(curve: dict, gamma: float, *, min_rise: float = 0.0, max_misfit: float = 0.05) -> list[str]:
    """What a fitted response cannot stand behind: a curve that does not rise with the
    level by more than ``min_rise`` between neighbouring levels (frames in the wrong
    order, repeated, or not of the ramp), or one that leaves the power law by more
    than ``max_misfit`` (of full light) at some level."""
    out = []
    xs = sorted(curve)
    ys = [0.0] + [curve[x] for x in xs] + [1.0]
    ls = [0.0] + xs + [1.0]
    flat = [f"{255 * ls[k]:g} -> {255 * ls[k + 1]:g}" for k in range(len(ys) - 1) if not ys[k + 1] - ys[k] > min_rise]
    if flat:
        out.append(f"the response does not rise between levels {', '.join(flat)} (responses "
                   f"{', '.join(f'{y:.3f}' for y in ys)}): frames repeated, out of order, or not of the ramp")
    worst = max(xs, key=lambda x: abs(curve[x] - x ** gamma))
    miss = abs(curve[worst] - worst ** gamma)
    if miss > max_misfit:
        out.append(f"the response at level {255 * worst:g} is {curve[worst]:.3f}, the fitted power law gives "
                   f"{worst ** gamma:.3f}: not a gamma curve")
    return out
