"""The decode's predicted errors checked against the view's own frames
(docs/design.md §18, item 6; docs/reconstruction.md, "Honest sigma").

A sample that carries both projector coordinates places its point twice over:
once on its ring's surface (rho alone) and once on its angle's (phi alone). The
two depths along the camera ray come from different frames; where the decode's
noise model (s_rho, s_tan: each depth's predicted standard deviation) is all
there is, their difference has the variance s_rho^2 + s_tan^2. What the model
cannot know shows up as more:

- the camera's noise is not the one assumed: each coordinate's predicted error
  is too small by a factor k (k_rho, k_tan >= 1);
- an error of a fixed size in projector pixels that no noise model holds: the
  harmonics of a projector's response nobody calibrated, which a 4-step phase
  code reads as phase (the angle's floor f_tan), and the sub-pixel bias of a
  ring edge (the projector's rasterisation, the camera's sampling: f_rho);
- the rig's calibration misses across the epipolar line (c, px): that direction
  holds no depth, so c widens the point's residual, not its depth;
- light bounced in (the indirect share, per coordinate) and the light's gradient
  across the image (``Samples.shading``): the camera's blur weighs every edge and
  fringe by the light around it, so where that changes fast (a shading edge, a
  highlight, a silhouette) the sample reads off its place by an amount that grows
  with the gradient. That is a camera-side error, the same size for both coordinates
  (one term, a px per unit gradient), and only its part across the epipolar line
  shows in the pairs: both coordinates take it, so the point placed by both does too.

Each term moves the depth difference in a known way per sample (through the
triangulation's own derivatives), so the five variances are one linear model of
each pair's variance, fitted by maximum likelihood under a Student-t of 5
degrees of freedom (robust to the few pairs a misread code throws far) and
read back as Gaussian variances (``T_SCALE``). The
sigmas are then sqrt(k^2 s^2 + f^2) per coordinate, and c is the floor of the
triangulation (``kernels.triangulation``). With a t of 5, a sigma fitted as the
Gaussian's sigma keeps median(|e| / sigma) at 0.67 and 0.3 % beyond three
sigmas where the errors are Gaussian, and ~0.63 and ~2 % where they have a t's tails.

Without the angle, a ring sample's neighbours check it instead
(:mod:`~ringscan.pipeline.reconstruct.neighbour_checks`), with this module's fit.
"""

from __future__ import annotations

import numpy as np

__all__ = ["ErrorModel", "fit_error_model", "fit_match_model", "region_scale", "group_scale", "apply_error_model", "sample_subset",
           "MAX_CHECK_SAMPLES", "MIN_PAIRS"]

MAX_CHECK_SAMPLES = 40000
"""Samples triangulated three more times for the fit (evenly spread over the
view): five numbers are fixed to ~1 % by 40k pairs; a full-size real view has
1.4M samples, whose triangulation is a view's main cost."""
MIN_PAIRS = 400
"""Fewer pairs with both depths than this: no fit (the decode's model as it is)."""
TILE_PX = 32
"""Camera tiles over which a calibration's miss is smooth (a decode's errors, noise,
a fringe's harmonics and an edge's bias, change from pixel to pixel)."""
MIN_TILE = 8
"""Fewer pairs in a tile than this: no estimate of the miss there."""
T_DOF = 5.0
"""Degrees of freedom of the Student-t likelihood."""
T_SCALE = 0.8566209142462031
"""The scale a t of ``T_DOF`` fits to a unit Gaussian (E[(nu + 1) z^2 / (nu S^2 + z^2)] = 1):
the model's variances are Gaussian ones, the likelihood's scale is this times
theirs, so that Gaussian errors get their own sigma back."""
REGION_PX = 32
"""Camera tiles over which a part of the view may need wider sigmas than the view's
model gives (an object beside a plane: its own facets, shadows, bounced light). On
Mitsuba's renders (docs/accuracy.md) 32 px tiles left fewer points beyond 3 sigma on the
object than 64 px (glossy Spot, angle: 7.7 -> 6.0 %; the corner's default 6.0 -> 5.7 %)."""
MIN_REGION_PAIRS = 64
"""Fewer pairs in a tile than this: the view's model alone there (64 pairs fix a
scale to ~18 %; a tile's factor is never below 1, so that noise only widens)."""
GROUP_SCALE_RANGE = (0.25, 64.0)
"""Bounds of a group's variance factor (``_group_scales``): half the view's sigma
at least, 8x at most: the fit on a group's pairs beyond them is taken as the bound."""
TERMS = ("k_rho", "k_tan", "floor_rho_px", "floor_tan_px", "floor_px")


class ErrorModel(dict):
    """``k_rho``, ``k_tan`` (factors >= 1 on the decode's predicted standard
    deviations), ``floor_rho_px``, ``floor_tan_px`` (projector px added in
    quadrature to each coordinate's), ``floor_px`` (across the epipolar line: the
    calibration's miss), ``indirect_rho_px``, ``indirect_tan_px`` (projector px per unit indirect
    share above the view's median), ``shading_rho_px`` = ``shading_tan_px`` (projector px per unit
    of the light's gradient, ``Samples.shading``; one term for both), ``pairs`` (samples that
    measured them), ``measured_by``
    (``angle``: each sample's two depths, :func:`fit_error_model`; ``neighbours``: a
    ring's neighbouring samples, :func:`fit_neighbour_model`; None: not measured), ``regions``
    (camera tiles whose pairs need a larger variance factor, :func:`region_scale`), ``reach``
    (``neighbours`` with a ring only: the variance factor of each class of samples the kept
    check does not reach, :func:`reach_scale`), ``lag_px``
    (``neighbours`` only: the spacing of the check kept, ``NEIGHBOUR_LAGS``), and the pairs'
    normalised disagreement under the decode's model and under the fitted one
    (``z_median`` / ``z_median_fitted``: a Gaussian gives 0.67; ``beyond_3`` /
    ``beyond_3_fitted``: 0.27 %)."""


def sample_subset(n: int, max_samples: int = MAX_CHECK_SAMPLES) -> np.ndarray:
    """Indices of at most ``max_samples`` of ``n`` samples, evenly spread (deterministic)."""
    if n <= max_samples:
        return np.arange(n, dtype=np.int64)
    return np.unique(np.linspace(0, n - 1, max_samples).round().astype(np.int64))


def identity_model(pairs: int = 0) -> ErrorModel:
    """The decode's model as it is (no term added)."""
    return ErrorModel(k_rho=1.0, k_tan=1.0, floor_rho_px=0.0, floor_tan_px=0.0, floor_px=0.0, pairs=int(pairs),
                      measured_by=None, regions=None, indirect_rho_px=0.0, indirect_tan_px=0.0, shading_rho_px=0.0,
                      shading_tan_px=0.0,
                      z_median=None, beyond_3=None, z_median_fitted=None, beyond_3_fitted=None)


def fit_error_model(depth_rho: np.ndarray, s_rho: np.ndarray, depth_tan: np.ndarray, s_tan: np.ndarray,
                    sigma_rho_px: np.ndarray, sigma_tan_px: np.ndarray, residual_var_px: np.ndarray,
                    uv: np.ndarray, indirect: np.ndarray | None = None,
                    rho_terms: tuple[float, float] | None = None, shading: np.ndarray | None = None) -> ErrorModel:
    """The error terms the decode's model misses, from the disagreement of the two depths.

    Args:
        depth_rho, depth_tan: (n,) each sample's depth along its camera ray (mm)
            placed by the ring alone and by the angle alone; NaN where it was not.
        s_rho, s_tan: (n,) their predicted standard deviations (mm).
        sigma_rho_px, sigma_tan_px: (n,) the decode's predicted standard deviations
            of rho and of the tangential position (projector px) those came from.
        residual_var_px: (n,) the predicted variance across the epipolar line
            (projector px^2) of the same sample placed by both; <= 0 where unknown.
        uv: (n, 2) the samples' camera positions (px): the calibration's miss is
            the part of the disagreement that is smooth over ``TILE_PX`` tiles.
        indirect: (n,) each sample's share of light that did not come straight from the
            projector, above the view's typical share (:attr:`Samples.indirect
            <ringscan.kernels.samples.Samples.indirect>` less its median, >= 0), or None:
            light bounced into a concave part shifts both coordinates there by an amount
            that grows with it (two more terms, in projector px per unit share).
        rho_terms: (k_rho, floor_rho_px) measured by the samples' own neighbours
            (:func:`fit_neighbour_model`), or None. Where the two coordinates' predicted
            errors scale alike (a dense code: both from the pixel's contrast), the pairs
            alone cannot tell whose error they disagree by; the neighbours can for rho,
            and the pairs then fit the angle's terms.
        shading: (n,) each sample's ``Samples.shading`` (per camera px: the light its
            surface sends back changing across the image, by its shading, texture or a
            highlight), or None: the camera's blur weighs every edge and fringe by that light,
            which moves the sample's place by an amount that grows with it: one more
            term, in projector px per unit gradient, the same for both coordinates (a
            camera-side shift; the pairs alone cannot tell whose coordinate it moved,
            fitted apart they put it on one: on Mitsuba's Spot through a tilted
            projector all on rho, and the points placed by both kept 61 % beyond 3 sigma
            where the gradient is steepest).

    Returns:
        :class:`ErrorModel` (:func:`identity_model` with fewer than ``MIN_PAIRS`` pairs).

    Size: one argument per per-sample quantity (each (n,), read together as the pairs'
    columns); a struct of them would only rename them.
    """
    a = [np.asarray(x, np.float64) for x in (depth_rho, s_rho, depth_tan, s_tan, sigma_rho_px, sigma_tan_px,
                                               residual_var_px)]
    dr, sr, dt, st, pr, pt, rv = a
    uv = np.asarray(uv, np.float64).reshape(-1, 2)
    m = np.isfinite(dr) & np.isfinite(dt) & np.isfinite(uv).all(axis=1)
    for x in (sr, st, pr, pt, rv):
        m &= np.isfinite(x) & (x > 0)
    n = int(np.count_nonzero(m))
    if n < MIN_PAIRS:
        return identity_model(n)
    gi = np.zeros(m.size) if indirect is None else np.asarray(indirect, np.float64)
    gs = np.zeros(m.size) if shading is None else np.asarray(shading, np.float64)
    m &= np.isfinite(gi) & np.isfinite(gs)
    n = int(np.count_nonzero(m))
    if n < MIN_PAIRS:
        return identity_model(n)
    dr, sr, dt, st, pr, pt, rv, uv, gi, gs = (x[m] for x in (dr, sr, dt, st, pr, pt, rv, uv, gi, gs))
    diff = dr - dt
    model_var = sr * sr + st * st
    # The calibration's miss: the signed residual across the epipolar line
    # (px; the depth difference over its depth per px there), smooth over tiles.
    gain = np.sqrt(model_var / rv)
    calib, calib_var = _smooth_part(diff / gain, uv)
    diff = diff - gain * calib
    if calib_var <= np.median(rv):
        # a miss within the decode's own error across the epipolar line: no floor (a
        # virtual rig, which fits its own images, measures ~1 % of it)
        calib_var = 0.0
    # the depth difference per projector px of each term: s / sigma_px for the two
    # coordinates; across the epipolar line the difference is the residual scaled
    # by sqrt(model_var / residual_var)
    X = np.stack([sr * sr, st * st, (sr / pr) ** 2, (st / pt) ** 2, (sr / pr * gi) ** 2, (st / pt * gi) ** 2,
                  (sr / pr * gs) ** 2 + (st / pt * gs) ** 2], axis=1)
    # a term whose covariate is 0 everywhere (no indirect light, no shading given) is 0
    used = np.array([True, True, True, True, np.any(gi > 0), np.any(gi > 0), np.any(gs > 0)])
    # k >= 1: the noise model is never shrunk
    lower = np.array([1.0, 1.0, 0.0, 0.0, 0.0, 0.0, 0.0])
    upper = np.full(7, np.inf)
    if rho_terms is not None:
        lower[0] = upper[0] = rho_terms[0] ** 2
        lower[2] = upper[2] = rho_terms[1] ** 2
    p = np.zeros(7)
    p[used] = _fit_variances(X[:, used], diff * diff, lower[used], upper[used] if rho_terms is not None else None)
    var = X @ p
    regions = _region_scales(diff * diff, var, uv)
    z0 = np.abs(dr - dt) / np.sqrt(model_var)
    z1 = np.abs(diff) / np.sqrt(var * region_scale(regions, uv))
    return ErrorModel(k_rho=float(np.sqrt(max(p[0], 1.0))), k_tan=float(np.sqrt(max(p[1], 1.0))),
                      floor_rho_px=float(np.sqrt(p[2])), floor_tan_px=float(np.sqrt(p[3])),
                      floor_px=float(np.sqrt(calib_var)), pairs=n, measured_by="angle", regions=regions,
                      indirect_rho_px=float(np.sqrt(p[4])), indirect_tan_px=float(np.sqrt(p[5])),
                      shading_rho_px=float(np.sqrt(p[6])), shading_tan_px=float(np.sqrt(p[6])),
                      z_median=float(np.median(z0)), beyond_3=float(np.mean(z0 > 3)),
                      z_median_fitted=float(np.median(z1)), beyond_3_fitted=float(np.mean(z1 > 3)))


def fit_match_model(dist: np.ndarray, slope2: np.ndarray, sigma1: np.ndarray, sigma2: np.ndarray,
                    uv: np.ndarray, *, floor: bool = True, max_distance_px: float = np.inf) -> dict:
    """What two cameras' matches miss of their own errors, from their distances to their epipolar lines.

    A match (camera 1's pixel, camera 2's position where its projector coordinate is the same) has one
    redundant number: its signed distance d from the epipolar line, with the predicted variance
    sigma2^2 + g^2 sigma1^2 (g: how far a camera-1 px moves the line). The part of d that is smooth over
    ``TILE_PX`` tiles is the calibration's miss (across the line: no depth) and is left out; the rest is fitted
    (Student-t, as :func:`fit_error_model`) by the variance k^2 (sigma2^2 + g^2 sigma1^2) + f^2 (1 + g^2): a
    factor k >= 1 on both sigmas and a floor f (px) added to each in quadrature. A decode's model can miss
    what neither camera's noise holds (a camera pixel over several projector pixels reads its place from
    the boundaries of coarser stripes, an error of the same size at every pixel there), and what the two
    cameras miss across the line they miss along it, where the depth is.

    Args:
        dist: (n,) signed distances (camera-2 px), NaN where unknown.
        slope2: (n,) g^2.
        sigma1, sigma2: (n,) the matches' predicted standard deviations (camera-1 px, camera-2 px).
        uv: (n, 2) camera 1's pixels.
        floor: False: the factor k alone (f = 0), for rays whose relative weights must stay as they are
            (a third ray, the projector's, that the fit does not see: all three take the one factor).
        max_distance_px: matches farther from their lines are left out (a mismatch, which the triangulation
            drops as inconsistent: the view's fit is of the points it keeps).

    Returns:
        {} with fewer than ``MIN_PAIRS`` usable matches; else {``k``, ``floor_px``, ``miss_px`` (the
        smooth part's RMS), ``pairs``, ``z_median``, ``beyond_3`` (|d| over its predicted sigma, as
        predicted), ``z_median_fitted``, ``beyond_3_fitted`` (the smooth part out, as fitted, with the
        regions' factors), ``regions`` (camera 1's tiles whose matches need a larger variance factor than
        the view's fit: :func:`region_scale`, as a one-camera view's model has them)}.
    """
    d, g2, s1, s2 = (np.asarray(x, np.float64).ravel() for x in (dist, slope2, sigma1, sigma2))
    uv = np.asarray(uv, np.float64).reshape(-1, 2)
    v = s2 * s2 + g2 * s1 * s1
    m = np.isfinite(d) & np.isfinite(g2) & np.isfinite(v) & (v > 0) & np.isfinite(uv).all(axis=1)
    m &= np.abs(np.where(np.isfinite(d), d, 0.0)) <= max_distance_px
    n = int(np.count_nonzero(m))
    if n < MIN_PAIRS:
        return {}
    d, g2, v, uv = d[m], g2[m], v[m], uv[m]
    calib, calib_var = _smooth_part(d, uv)
    r = d - calib
    X = np.stack([v, 1.0 + g2], axis=1)
    if floor:
        p = _fit_variances(X, r * r, np.array([1.0, 0.0]))
    else:
        X = X[:, :1]
        p = np.r_[_fit_variances(X, r * r, np.array([1.0])), 0.0]
    z0 = np.abs(d) / np.sqrt(v)
    fitted = X @ p[:X.shape[1]]
    regions = _region_scales(r * r, fitted, uv)
    z1 = np.abs(r) / np.sqrt(fitted * region_scale(regions, uv))
    return {"k": float(np.sqrt(max(p[0], 1.0))), "floor_px": float(np.sqrt(max(p[1], 0.0))),
            "miss_px": float(np.sqrt(calib_var)), "pairs": n,
            "z_median": float(np.median(z0)), "beyond_3": float(np.mean(z0 > 3)),
            "z_median_fitted": float(np.median(z1)), "beyond_3_fitted": float(np.mean(z1 > 3)), "regions": regions}


def _region_scales(d2: np.ndarray, var: np.ndarray, uv: np.ndarray) -> dict:
    """Where a part of the view disagrees more than the view's model says (an object's
    grazing facets and shadow edges beside a plane that holds most pairs, light bounced
    into a concave corner): per ``REGION_PX`` camera tile with at least
    ``MIN_REGION_PAIRS`` pairs, the factor m >= 1 on the variances that the tile's pairs
    fit (the same Student-t, one scale: the fixed point of its likelihood). Never below 1:
    the view's model is the least a sample gets.

    Returns: {"tile_px": REGION_PX, "scales": [[tile x, tile y, m], ...] (tiles with m > 1)}.
    """
    key = np.floor(uv / REGION_PX).astype(np.int64)
    tile = key[:, 0] * 1_000_003 + key[:, 1]
    _, inv, counts = np.unique(tile, return_inverse=True, return_counts=True)
    order = np.argsort(inv, kind="stable")  # a tile's pairs a slice, in their order (as a mask takes them)
    starts = np.r_[0, np.cumsum(counts)[:-1]]
    u_all = (d2 / (T_SCALE * T_SCALE * np.maximum(var, 1e-300)))[order]
    scales = []
    big = np.flatnonzero(counts >= MIN_REGION_PAIRS)
    for t, m in zip(big, _t_scales(u_all, starts[big], counts[big])):
        if m > 1.0:  # [tile x, tile y, m]
            scales.append([*map(int, key[order[starts[t]]]), round(float(m), 4)])
    return {"tile_px": REGION_PX, "scales": scales}


def _t_scales(u: np.ndarray, starts: np.ndarray, counts: np.ndarray) -> np.ndarray:
    """:func:`_t_scale` of each slice u[starts[i]:starts[i] + counts[i]], all at once (each slice's
    iteration stops where its own would; the means summed in order, not pairwise: the same factors
    to ~1e-15)."""
    if starts.size == 0:
        return np.zeros(0)
    first = np.r_[0, np.cumsum(counts)[:-1]]
    seg = np.repeat(np.arange(starts.size), counts)
    uu = u[np.repeat(starts - first, counts) + np.arange(seg.size)]
    m = np.ones(starts.size)
    live = np.ones(starts.size, bool)
    for _ in range(50):
        m_new = np.add.reduceat((T_DOF + 1) * uu / (T_DOF + uu / m[seg]), first) / counts
        done = live & (np.abs(m_new - m) <= 1e-4 * m)
        m = np.where(live, m_new, m)
        live &= ~done
        if not live.any():
            break
    return m


def _t_scale(u: np.ndarray) -> float:
    """The variance factor m that squared, normalised differences ``u`` (d^2 / (T_SCALE^2
    var)) fit under the Student-t of ``T_DOF`` degrees of freedom: the fixed point of its
    likelihood, m = mean((nu + 1) u / (nu + u / m))."""
    m = 1.0
    for _ in range(50):
        m_new = float(np.mean((T_DOF + 1) * u / (T_DOF + u / m)))
        if abs(m_new - m) <= 1e-4 * m:
            return m_new
        m = m_new
    return m


def _group_scales(d2: np.ndarray, var: np.ndarray, group: np.ndarray) -> dict:
    """Samples the codec says err differently (``Codec.error_groups``: the pattern whose
    edge places them) get a variance factor each: per group with at least ``MIN_PAIRS``
    checked samples, the factor its pairs fit (``_t_scale``; 1 for the others), within
    ``GROUP_SCALE_RANGE``. Returns [[group, factor], ...]."""
    u_all = d2 / (T_SCALE * T_SCALE * np.maximum(var, 1e-300))
    out = []
    for g in np.unique(group):
        m = group == g
        if g >= 0 and np.count_nonzero(m) >= MIN_PAIRS:
            out.append([int(g), round(float(np.clip(_t_scale(u_all[m]), *GROUP_SCALE_RANGE)), 4)])
    return out


def group_scale(groups: list | None, group: np.ndarray | None) -> np.ndarray | float:
    """Each sample's variance factor from :func:`_group_scales` ([[group, factor], ...]; 1
    where its group has none)."""
    if not groups or group is None:
        return 1.0
    group = np.asarray(group, np.int64)
    table = np.ones(max(max(g for g, _ in groups), int(np.max(group, initial=0))) + 1)
    for g, m in groups:
        table[g] = m
    return np.where(group >= 0, table[np.maximum(group, 0)], 1.0)


def region_scale(regions: dict | None, uv: np.ndarray) -> np.ndarray:
    """(n,) each sample's variance factor from :func:`_region_scales`' tiles (1 outside them)."""
    uv = np.asarray(uv, np.float64).reshape(-1, 2)
    out = np.ones(len(uv))
    if not regions or not regions.get("scales"):
        return out
    table = np.asarray(regions["scales"], np.float64)
    px = float(regions["tile_px"])
    key = np.floor(uv / px).astype(np.int64)
    code = key[:, 0] * 1_000_003 + key[:, 1]
    tcode = table[:, 0].astype(np.int64) * 1_000_003 + table[:, 1].astype(np.int64)
    order = np.argsort(tcode)
    at = np.minimum(np.searchsorted(tcode[order], code), len(tcode) - 1)
    hit = tcode[order][at] == code
    out[hit] = table[order][at[hit], 2]
    return out


def _fit_variances(X: np.ndarray, d2: np.ndarray, lower: np.ndarray, upper: np.ndarray | None = None) -> np.ndarray:
    """The variances P (>= ``lower``, <= ``upper`` where given: equal bounds fix a term)
    of the model var_i = X_i @ P that fit the squared differences ``d2`` (n,) best under
    a Student-t of ``T_DOF`` degrees of freedom read back as Gaussian variances
    (``T_SCALE``). X: (n, m) each term's variance per unit."""
    n = d2.size
    # in units where every column's and the squared differences' medians are 1:
    # var = Xs @ q with q = P * col / d2_scale
    # (each column's mean: the indirect-light terms act on a few samples and are 0 or a trace on the rest;
    # scaled by their median, ~1e-6 of the other terms' units, L-BFGS-B stopped far from the likelihood's
    # best: on a sphere in noise k_rho 4.6 where truth and the best said ~3)
    col = np.mean(X, axis=0)
    col[~(col > 0)] = 1.0
    d2_scale = max(float(np.median(d2)), 1e-300)
    Xs = X / col
    d2 = d2 / d2_scale
    lower = lower * col / d2_scale
    bounds = [(lo, None) for lo in lower]
    if upper is not None:
        hi = np.asarray(upper, np.float64) * col / d2_scale
        bounds = [(lo, h if np.isfinite(h) else None) for lo, h in zip(lower, hi)]

    s2 = T_SCALE * T_SCALE
    c = d2 / T_DOF

    def nll(q):
        var = np.maximum(s2 * (Xs @ q), 1e-300)
        return (0.5 * np.sum(np.log(var)) + 0.5 * (T_DOF + 1) * np.sum(np.log1p(c / var))) / n

    def derivatives(q):  # the gradient and the Hessian of nll
        var = np.maximum(s2 * (Xs @ q), 1e-300)
        vc = var + c
        g_var = 0.5 / var - 0.5 * (T_DOF + 1) * c / (var * vc)
        h_var = -0.5 / (var * var) + 0.5 * (T_DOF + 1) * c * (2 * var + c) / (var * var * vc * vc)
        return s2 * (Xs.T @ g_var) / n, (s2 * s2 / n) * (Xs.T @ (h_var[:, None] * Xs))

    lo = np.array([b[0] for b in bounds], np.float64)
    hi = np.array([np.inf if b[1] is None else b[1] for b in bounds], np.float64)
    start = np.where(np.isfinite(hi), 0.5 * (lo + hi), lo + 0.2)
    q = minimize_in_box(nll, derivatives, start, lo, hi)
    return np.maximum(q, lower) * d2_scale / col


def minimize_in_box(f, derivatives, x0: np.ndarray, lo: np.ndarray, hi: np.ndarray, *,
                    max_iter: int = 200) -> np.ndarray:
    """The minimum of a smooth function of a few variables within lo <= x <= hi (hi may hold inf; lo = hi
    fixes a variable), by projected Newton steps: ``f(x)`` its value, ``derivatives(x)`` its gradient (m,) and
    Hessian (m, m). A variable at a bound whose gradient pushes it outward is held there; the others take their
    block's Newton step (the Hessian made positive definite by the least multiple of the identity that does
    it), projected into the box and halved until f falls by Armijo's rule. Stops where the projected gradient
    is below 1e-10 (the fit's units: its values and variables are of order 1) or f no longer falls.

    NumPy only: SciPy's optimisers (L-BFGS-B, the fit's solver before) cost a ``ringscan reconstruct``
    process 0.27 s of imports, a fifth of a one-view run; their optimum is this one's to ~1e-9 (tested)."""
    x = np.clip(np.asarray(x0, np.float64), lo, hi)
    movable = hi > lo
    fx = f(x)
    for _ in range(max_iter):
        g, H = derivatives(x)
        free = movable & ~(((x <= lo) & (g > 0)) | ((x >= hi) & (g < 0)))
        if not free.any() or np.max(np.abs(g[free])) <= 1e-10:
            break
        Hf, gf = H[np.ix_(free, free)], g[free]
        shift = 0.0
        while True:
            try:
                L = np.linalg.cholesky(Hf + shift * np.eye(gf.size))
                break
            except np.linalg.LinAlgError:
                shift = max(2.0 * shift, 1e-10 * max(float(np.max(np.abs(np.diag(Hf)))), 1e-12))
        step = np.zeros_like(x)
        step[free] = -np.linalg.solve(L.T, np.linalg.solve(L, gf))
        t = 1.0
        while True:
            xn = np.clip(x + t * step, lo, hi)
            fn = f(xn)
            if fn <= fx + 1e-4 * min(float(g @ (xn - x)), 0.0):
                break
            t *= 0.5
            if t < 1e-12:
                return x
        done = fx - fn <= 1e-15 * max(1.0, abs(fx))
        x, fx = xn, fn
        if done:
            break
    return x


def _tile_medians(x: np.ndarray, inv: np.ndarray, starts: np.ndarray, counts: np.ndarray) -> np.ndarray:
    """Each tile's ``np.median`` of ``x`` (tile ``inv`` of each value; the tiles' ``starts`` and ``counts`` in
    tile order), from one sort of all the values by tile and value: the middle value, or the mean of the two
    middle ones as np.median takes it ((a + b) / 2)."""
    v = x[np.lexsort((x, inv))]
    hi = v[starts + counts // 2]
    lo = v[starts + np.maximum(counts - 1, 0) // 2]
    return np.where(counts % 2 == 1, hi, (lo + hi) / 2)


def _smooth_part(r: np.ndarray, uv: np.ndarray) -> tuple[np.ndarray, float]:
    """Each sample's share of the residual field that is smooth over ``TILE_PX``
    camera tiles (the median of its tile's signed residuals, 0 in tiles of fewer than
    ``MIN_TILE`` samples), and that field's variance less what its medians' own noise
    gives (>= 0)."""
    key = np.floor(uv / TILE_PX).astype(np.int64)
    tile = key[:, 0] * 1_000_003 + key[:, 1]
    _, inv, counts = np.unique(tile, return_inverse=True, return_counts=True)
    starts = np.r_[0, np.cumsum(counts)[:-1]]
    big = counts >= MIN_TILE
    med = np.where(big, _tile_medians(r, inv, starts, counts), 0.0)
    mad = _tile_medians(np.abs(r - med[inv]), inv, starts, counts) / 0.6745
    noise = np.where(big, 1.571 * mad * mad / counts, 0.0)  # a median's variance, pi / 2 sigma^2 / n
    field = med[inv]
    used = counts[inv] >= MIN_TILE
    if not used.any():
        return field, 0.0
    return field, max(float(np.mean(field[used] ** 2) - np.mean(noise[inv][used])), 0.0)


def apply_error_model(sigma_px: np.ndarray, k: float, floor_px: float, *, indirect_px: float = 0.0,
                      indirect: np.ndarray | None = None, shading_px: float = 0.0,
                      shading: np.ndarray | None = None) -> np.ndarray:
    """sqrt(k^2 sigma^2 + floor^2 + (indirect_px * indirect)^2 + (shading_px * shading)^2), float32
    (``indirect``: (n,) each sample's indirect-light share above the view's; ``shading``: (n,) its
    light's relative gradient, ``Samples.shading``; :func:`fit_error_model`)."""
    s = np.asarray(sigma_px, np.float64)
    var = (k * s) ** 2 + floor_px ** 2
    if indirect_px > 0 and indirect is not None:
        var = var + (indirect_px * np.asarray(indirect, np.float64)) ** 2
    if shading_px > 0 and shading is not None:
        var = var + (shading_px * np.asarray(shading, np.float64)) ** 2
    return np.sqrt(var).astype(np.float32)
