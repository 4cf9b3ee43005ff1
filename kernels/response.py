"""The camera's response tables for linearising recorded values (NumPy; no kernels, so that a codec that
only needs the tables, the angle code's, loads none of the phase decoder's kernels)."""

from __future__ import annotations

import numpy as np

__all__ = ["RESPONSE_FLOOR", "response_tables"]

RESPONSE_FLOOR = 0.02
"""Recorded values below this fraction of full scale get the weight of this value
(the slope of a gamma curve vanishes at 0; sensor noise does not)."""


def response_tables(full_scale: int, *, camera_gamma: float = 1.0, weighted: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """Linearisation and weight tables for recorded values 0..full_scale.

    lut[r] = (r / full)^gamma (linear irradiance, full white = 1); wlut[r] =
    1 / (d lut / d r)^2 up to a constant (the inverse noise variance of the
    linearised value under additive sensor noise), the slope taken at no less
    than ``RESPONSE_FLOOR`` of full scale; all ones when not ``weighted``.

    Returns:
        (lut, wlut), two (full_scale + 1,) float32 arrays.
    """
    if full_scale not in (255, 65535):
        raise ValueError(f"response_tables: full_scale must be 255 or 65535, got {full_scale}")
    g = float(camera_gamma)
    if not np.isfinite(g) or g <= 0:
        raise ValueError(f"response_tables: camera_gamma must be > 0, got {camera_gamma}")
    x = np.arange(full_scale + 1, dtype=np.float64) / full_scale
    lut = x ** g
    if weighted and g != 1.0:
        xf = np.maximum(x, RESPONSE_FLOOR)
        wlut = xf ** (-2.0 * (g - 1.0))
        wlut /= wlut.max()
    else:
        wlut = np.ones_like(x)
    return lut.astype(np.float32), wlut.astype(np.float32)
