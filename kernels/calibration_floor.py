"""The calibration floor (docs/reconstruction.md, "Calibration floor"): the projector-pixel error across
the epipolar line that the decode's own model does not explain, from the residuals of the samples
triangulated with both coordinates (``kernels.triangulation``), on their device: the usable samples
compacted, their order statistics by sorts, and each bisection step's median test by partial counts
(NumPy's medians to the bit; a test keeps the former NumPy body as the statement)."""

from __future__ import annotations

import numpy as np
import warp as wp

from ringscan.kernels.compact import gather, median, median64, nonzero_indices, percentile32, sort_finite
from ringscan.kernels.launch import default_threads, launch_spans
from ringscan.kernels.triangulation import Triangulation

wp.set_module_options({"enable_backward": False})  # no gradients are taken here: no adjoint code to compile

__all__ = ["CHI2_1_MEDIAN", "calibration_floor", "residual_floor"]

CHI2_1_MEDIAN = 0.454936423119572
"""Median of a chi-square variable with one degree of freedom."""
FLOOR_SPAN = wp.constant(4096)
"""Samples a row of the calibration floor's partial sums counts (one thread a row)."""


# ----------------------------------------------------------------------------- kernels


@wp.kernel
def floor_terms_kernel(
    residual: wp.array(dtype=wp.float32),
    residual_var: wp.array(dtype=wp.float32),
    i0: int,
    usable: wp.array(dtype=wp.int32),
    r2: wp.array(dtype=wp.float64),
    v: wp.array(dtype=wp.float64),
):
    """Sample i0 + tid's place in the calibration floor (:func:`calibration_floor`): usable where its
    residual variance is > 0 and its residual finite and >= 0; its squared residual and variance in
    float64. residual, residual_var (n,) float32: read; usable (n,) int32, r2, v (n,) float64: written."""
    i = i0 + wp.tid()
    r = residual[i]
    var = residual_var[i]
    usable[i] = wp.where(var > 0.0 and r >= 0.0 and wp.isfinite(r), 1, 0)
    rr = wp.float64(r)
    r2[i] = rr * rr
    v[i] = wp.float64(var)


@wp.kernel
def floor_count_kernel(
    r2: wp.array(dtype=wp.float64),
    v: wp.array(dtype=wp.float64),
    c2: wp.float64,
    level: wp.float64,
    i0: int,
    part: wp.array2d(dtype=wp.float64),
):
    """Row i0 + tid of the bisection's partial sums over FLOOR_SPAN samples of x = r2 / (v + c2): how many
    x exceed ``level``, the largest x at or below it, the smallest above it, the largest r2. r2, v (m,)
    float64: read; part (rows, 4) float64: written."""
    row = i0 + wp.tid()
    above = wp.float64(0.0)
    below_max = wp.float64(-1.0)
    above_min = wp.float64(1.0e308)
    r2_max = wp.float64(0.0)
    end = wp.min((row + 1) * FLOOR_SPAN, r2.shape[0])
    for i in range(row * FLOOR_SPAN, end):
        x = r2[i] / (v[i] + c2)
        if x > level:
            above += wp.float64(1.0)
            above_min = wp.min(above_min, x)
        else:
            below_max = wp.max(below_max, x)
        r2_max = wp.max(r2_max, r2[i])
    part[row, 0] = above
    part[row, 1] = below_max
    part[row, 2] = above_min
    part[row, 3] = r2_max


@wp.kernel
def chi2_kernel(r2: wp.array(dtype=wp.float64), v: wp.array(dtype=wp.float64), i0: int,
                x: wp.array(dtype=wp.float64)):
    """x = r2 / v (the chi-squares without a floor). r2, v (m,) float64: read; x (m,) float64: written."""
    i = i0 + wp.tid()
    x[i] = r2[i] / v[i]


# ----------------------------------------------------------------------------- host


def calibration_floor(tri: Triangulation, *, threads: int | None = None) -> tuple[float, dict]:
    """The projector-pixel error the decode's own model does not explain, across the epipolar line: the
    triangulation's ``residual`` and ``residual_var`` through :func:`residual_floor` (its docstring)."""
    return residual_floor(tri.residual, tri.residual_var, threads=threads)


def residual_floor(residual: wp.array, residual_var: wp.array, *,
                   threads: int | None = None) -> tuple[float, dict]:
    """The projector-pixel error the decode's own model does not explain, from residuals with one degree of
    freedom each and their predicted variances.

    Each sample triangulated with both coordinates has one degree of freedom
    left: its residual (the distance between the observed projector pixel and the
    point's own) divided by the decode's predicted standard deviation in that
    direction is a unit normal variable where the model is right. On a real rig
    the calibration adds an error of its own, seen across the epipolar line; the
    floor c is the standard deviation that, added there to every sample's, brings
    the median chi-square back to its expected value (0 where it already is).
    Along the epipolar line a calibration error cannot be seen in one view.

    On the triangulation's device: the usable samples compacted, their order statistics by sorts,
    and each bisection step's test of the median by counts (how many chi-squares exceed the
    level, and the two nearest it where the count is half: the median of an even count is their
    mean): the values NumPy's medians give, with partial sums read, not the samples.

    residual, residual_var: (n,) float32 each sample's residual (px, >= 0) and its predicted variance
    (px^2); a sample is usable where the variance is > 0 and the residual finite and >= 0 (a two-camera
    view's projector check, ``kernels.stereo_rays.projector_misses``, reads its residuals so too).

    Returns:
        (c in projector px, {"samples", "residual_px_median", "residual_px_p95",
        "chi2_median"}); c = 0 and an empty dict without such samples.
    """
    n = residual.shape[0]
    dev = residual.device
    threads = default_threads() if threads is None else threads
    if n == 0:
        return 0.0, {}
    usable = wp.empty(n, dtype=wp.int32, device=dev)
    r2_all = wp.empty(n, dtype=wp.float64, device=dev)
    v_all = wp.empty(n, dtype=wp.float64, device=dev)
    launch_spans(floor_terms_kernel, n, lambda i0: [residual, residual_var, i0], [usable, r2_all, v_all], dev,
                 threads)
    idx = nonzero_indices(usable, threads=threads)
    m = idx.shape[0]
    if m < 20:
        return 0.0, {}
    res = gather(residual, idx, threads=threads)
    r2, v = gather(r2_all, idx, threads=threads), gather(v_all, idx, threads=threads)
    rows = (m + FLOOR_SPAN - 1) // FLOOR_SPAN
    part = wp.empty((rows, 4), dtype=wp.float64, device=dev)

    def counts(c: float, level: float) -> np.ndarray:  # the partial sums at c, summed over the rows
        launch_spans(floor_count_kernel, rows, lambda i0: [r2, v, wp.float64(c * c), wp.float64(level), i0], [part],
                     dev, threads, min_span=1)
        p = part.numpy()
        return np.array([p[:, 0].sum(), p[:, 1].max(), p[:, 2].min(), p[:, 3].max()])

    def median_above(c: float) -> bool:  # np.median(r2 / (v + c * c)) > CHI2_1_MEDIAN, by counts
        above, below_max, above_min, _ = counts(c, CHI2_1_MEDIAN)
        if m % 2:
            return above >= (m + 1) // 2
        if above != m // 2:
            return above > m // 2
        return float(np.mean([below_max, above_min])) > CHI2_1_MEDIAN

    x = wp.empty(m, dtype=wp.float64, device=dev)
    launch_spans(chi2_kernel, m, lambda i0: [r2, v, i0], [x], dev, threads)
    ranked = sort_finite(res)
    stats = {"samples": int(m), "residual_px_median": median(ranked, dtype=np.float32, presorted=True),
             "residual_px_p95": percentile32(ranked, 95, presorted=True), "chi2_median": median64(x)}
    if stats["chi2_median"] <= CHI2_1_MEDIAN:
        return 0.0, stats
    lo, hi = 0.0, float(np.sqrt(counts(0.0, CHI2_1_MEDIAN)[3])) + 1e-9
    for _ in range(60):
        c = 0.5 * (lo + hi)
        if median_above(c):
            lo = c
        else:
            hi = c
    return hi, stats
