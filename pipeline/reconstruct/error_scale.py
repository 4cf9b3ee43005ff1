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
  holds no depth, so c widens the point's residual, not its depth.

Each term moves the depth difference in a known way per sample (through the
triangulation's own derivatives), so the five variances are one linear model of
each pair's variance, fitted by maximum likelihood under a Student-t of 5
degrees of freedom (robust to the few pairs a misread code throws far) and
read back as Gaussian variances (``T_SCALE``). The
sigmas are then sqrt(k^2 s^2 + f^2) per coordinate, and c is the floor of the
triangulation (``kernels.triangulation``). With a t of 5, a sigma fitted as the
Gaussian's sigma keeps median(|e| / sigma) at 0.67 and 0.3 % beyond three
sigmas where the errors are Gaussian, and ~0.63 and ~2 % where they have a t's tails.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["ErrorModel", "fit_error_model", "region_scale", "fit_neighbour_model", "widen_depth_sigma", "sample_subset", "MAX_CHECK_SAMPLES", "MIN_PAIRS"]

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
    calibration's miss), ``pairs`` (samples that measured them), ``measured_by``
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
                      measured_by=None, regions=None, indirect_rho_px=0.0, indirect_tan_px=0.0, z_median=None, beyond_3=None, z_median_fitted=None, beyond_3_fitted=None)


def fit_error_model(depth_rho: np.ndarray, s_rho: np.ndarray, depth_tan: np.ndarray, s_tan: np.ndarray,
                    sigma_rho_px: np.ndarray, sigma_tan_px: np.ndarray, residual_var_px: np.ndarray,
                    uv: np.ndarray, indirect: np.ndarray | None = None,
                    rho_terms: tuple[float, float] | None = None) -> ErrorModel:
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
    m &= np.isfinite(gi)
    n = int(np.count_nonzero(m))
    if n < MIN_PAIRS:
        return identity_model(n)
    dr, sr, dt, st, pr, pt, rv, uv, gi = (x[m] for x in (dr, sr, dt, st, pr, pt, rv, uv, gi))
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
    X = np.stack([sr * sr, st * st, (sr / pr) ** 2, (st / pt) ** 2, (sr / pr * gi) ** 2, (st / pt * gi) ** 2],
                 axis=1)
    terms = 6 if np.any(gi > 0) else 4  # no indirect light anywhere: its terms are 0
    # k >= 1: the noise model is never shrunk
    lower = np.array([1.0, 1.0, 0.0, 0.0, 0.0, 0.0])[:terms]
    upper = None
    if rho_terms is not None:
        upper = np.full(terms, np.inf)
        lower[0] = upper[0] = rho_terms[0] ** 2
        lower[2] = upper[2] = rho_terms[1] ** 2
    p = np.zeros(6)
    p[:terms] = _fit_variances(X[:, :terms], diff * diff, lower, upper)
    var = X @ p
    regions = _region_scales(diff * diff, var, uv)
    z0 = np.abs(dr - dt) / np.sqrt(model_var)
    z1 = np.abs(diff) / np.sqrt(var * region_scale(regions, uv))
    return ErrorModel(k_rho=float(np.sqrt(max(p[0], 1.0))), k_tan=float(np.sqrt(max(p[1], 1.0))),
                      floor_rho_px=float(np.sqrt(p[2])), floor_tan_px=float(np.sqrt(p[3])),
                      floor_px=float(np.sqrt(calib_var)), pairs=n, measured_by="angle", regions=regions,
                      indirect_rho_px=float(np.sqrt(p[4])), indirect_tan_px=float(np.sqrt(p[5])),
                      z_median=float(np.median(z0)), beyond_3=float(np.mean(z0 > 3)),
                      z_median_fitted=float(np.median(z1)), beyond_3_fitted=float(np.mean(z1 > 3)))


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
    for t in np.flatnonzero(counts >= MIN_REGION_PAIRS):
        m = _t_scale(u_all[starts[t]:starts[t] + counts[t]])
        if m > 1.0:  # [tile x, tile y, m]
            scales.append([*map(int, key[order[starts[t]]]), round(m, 4)])
    return {"tile_px": REGION_PX, "scales": scales}


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


NEIGHBOUR_LAGS = (1, 2, 4, 8)
"""Spacings (camera px along a ring; along the pixel grid for a dense code) at which
each checked sample meets its neighbours: at 1 px, two on either side through a line;
at k >= 2, four (at -2k, -k, k, 2k) through a cubic, which a smooth surface's depth
follows over 4k px to far below the decode's errors. Errors that neighbouring pixels
share (a blur spreading one pixel's noise over its neighbours, a sharp projector's
staircase running over several pixels) cancel in the 1 px check and errors that
alternate from pixel to pixel read too large in it; from ~3 px apart the reading stays
level (ringscan's renderer: gray-rings 1.31, 1.47, 1.55, 1.54, 1.58 at 1, 2, 3, 4, 6 px
on Spot; phase-rings under a sharp projector 113, 61, 47, 45, 45): the widest check
that can be made is kept (fit_neighbour_model). The 1 px check is the fallback where
rings are too short or broken for four neighbours. Along a ring, 8 px sees what a
washed-out pattern's edges share over several pixels: gray-rings without the angle on
ringscan's far faint plane, median |e|/sigma 1.16 and 9.4 % beyond 3 sigma with 4 px
at most, 1.09 and 7.3 % with 8, every other condition as before or nearer 0.67 (16 px:
1.07 and 6.7 %, but the far dark plane's fewer checks read it 5.4 % beyond). A dense
code stops at ``DENSE_MAX_LAG_PX``."""

REGION_MAX_LAG_PX = 4
"""The widest check a region's factor (``_region_scales``) is measured with: an object's
facet beside a plane holds more 4 px checks than 8 px ones (a planted 2x corner of a
synthetic view read 2.4x in variance with 8 px, 4x with 4)."""

DENSE_MAX_LAG_PX = 4
"""The widest check of a dense code (along the pixel grid): its errors are so small
(phase-rings: 0.002 mm on Spot) that a curved surface's departure from the cubic over
32 px reads as error at 8 px (median |e|/sigma 0.31-0.37: sigma 2x too wide)."""


def _same_ring_at(ring, at_pixel, width, height, centre, xx, yy):
    """(idx, hit): the sample at pixel (xx, yy) (m,) of each ``centre`` sample (-1 for none
    or outside the camera), and whether it is of the centre's ring."""
    inside = (xx >= 0) & (xx < width) & (yy >= 0) & (yy < height)
    idx = np.where(inside, at_pixel[np.where(inside, yy * width + xx, 0)], -1)
    return idx, (idx >= 0) & (ring[np.maximum(idx, 0)] == ring[centre])


def _lag_nodes(uv, ring, at_pixel, width, centre, direction, k):
    """(m, 4) sample indices (-1: none) of the same-ring samples nearest to
    uv[centre] + s * k * direction for s = -2, -1, 1, 2 (each within the 5x5 pixels
    around its target and within 0.3 k of it), and (m, 4) their signed places along
    ``direction`` (px). ``at_pixel``: (H * W,) a sample index at each camera pixel (-1:
    none; of two rings' samples at one pixel, one)."""
    m = centre.size
    height = at_pixel.size // width
    nodes = np.full((m, 4), -1, np.int64)
    place = np.zeros((m, 4))
    for j, step in enumerate((-2, -1, 1, 2)):
        target = uv[centre] + (step * k) * direction
        tx, ty = np.rint(target[:, 0]).astype(np.int64), np.rint(target[:, 1]).astype(np.int64)
        best = np.full(m, np.inf)
        for dy in range(-2, 3):
            for dx in range(-2, 3):
                idx, hit = _same_ring_at(ring, at_pixel, width, height, centre, tx + dx, ty + dy)
                dist = np.where(hit, np.linalg.norm(uv[np.maximum(idx, 0)] - target, axis=1), np.inf)
                better = dist < best
                best[better] = dist[better]
                nodes[better, j] = idx[better]
        nodes[best > max(1.5, 0.5 * k), j] = -1
        place[:, j] = np.einsum("ij,ij->i", uv[np.maximum(nodes[:, j], 0)] - uv[centre], direction)
    return nodes, place


def _ring_directions(uv, ring, at_pixel, width, centre):
    """(the centres with at least two other samples of their ring in the 5x5 pixels
    around them, (m, 2) the unit direction of the ring there: the principal axis of
    those samples' positions)."""
    height = at_pixel.size // width
    x, y = np.rint(uv[centre, 0]).astype(np.int64), np.rint(uv[centre, 1]).astype(np.int64)
    count = np.zeros(centre.size)
    mean = np.zeros((centre.size, 2))
    cov = np.zeros((centre.size, 3))  # xx, xy, yy
    for dy in range(-2, 3):
        for dx in range(-2, 3):
            idx, hit = _same_ring_at(ring, at_pixel, width, height, centre, x + dx, y + dy)
            q = np.where(hit[:, None], uv[np.maximum(idx, 0)] - uv[centre], 0.0)
            count += hit
            mean += q
            cov += np.stack([q[:, 0] ** 2, q[:, 0] * q[:, 1], q[:, 1] ** 2], 1)
    keep = count >= 3  # the centre itself and two more
    n = np.maximum(count, 1)[:, None]
    mean /= n
    cxx, cxy, cyy = (cov / n).T
    cxx, cxy, cyy = cxx - mean[:, 0] ** 2, cxy - mean[:, 0] * mean[:, 1], cyy - mean[:, 1] ** 2
    angle = 0.5 * np.arctan2(2 * cxy, cxx - cyy)
    direction = np.stack([np.cos(angle), np.sin(angle)], 1)
    return centre[keep], direction[keep]


def _lagrange_at_zero(place: np.ndarray) -> np.ndarray:
    """(m, n) weights w of the polynomial through n nodes at ``place`` (m, n), read at 0."""
    w = np.ones_like(place)
    n = place.shape[1]
    for i in range(n):
        for j in range(n):
            if i != j:
                w[:, i] *= -place[:, j] / (place[:, i] - place[:, j])
    return w


@dataclass(frozen=True)
class _RingIndex:
    """Where the usable samples of a view are: by ring and pixel, and by pixel."""

    ring: np.ndarray
    """(n,) int64 each sample's ring (0 for a dense code)."""
    x: np.ndarray
    """(n,) int64 its camera column."""
    y: np.ndarray
    """(n,) int64 its camera row."""
    width: int
    """Camera width (px)."""
    npix: int
    """More than any pixel index: the key's stride per ring."""
    key: np.ndarray
    """(m,) sorted ring * npix + pixel of the usable samples."""
    order: np.ndarray
    """(m,) the sample index of each key."""
    at_pixel: np.ndarray
    """(npix,) a usable sample's index at each pixel, -1 for none (of two rings' at one pixel, one)."""


def _ring_index(ring: np.ndarray, pixel: np.ndarray, usable: np.ndarray, width: int) -> _RingIndex:
    """The :class:`_RingIndex` of the ``usable`` samples (indices)."""
    npix = int(pixel.max()) + width + 2
    key = ring[usable] * npix + pixel[usable]
    o = np.argsort(key, kind="stable")
    at_pixel = np.full(npix, -1, np.int64)
    at_pixel[pixel[usable]] = usable
    return _RingIndex(ring=ring, x=pixel % width, y=pixel // width, width=width, npix=npix, key=key[o],
                      order=usable[o], at_pixel=at_pixel)


def _next_neighbours(uv: np.ndarray, idx: _RingIndex, centre: np.ndarray):
    """(c, a, b): the ``centre`` samples that have two samples of their own ring among
    their 8 neighbouring pixels most nearly on opposite sides (at least 120 degrees
    apart), and those two."""
    offsets = [(dx, dy) for dy in (-1, 0, 1) for dx in (-1, 0, 1) if dx or dy]
    nb = np.full((centre.size, len(offsets)), -1, np.int64)
    for j, (dx, dy) in enumerate(offsets):
        xx, yy = idx.x[centre] + dx, idx.y[centre] + dy
        want = idx.ring[centre] * idx.npix + yy * idx.width + xx
        at = np.minimum(np.searchsorted(idx.key, want), idx.key.size - 1)
        hit = (idx.key[at] == want) & (xx >= 0) & (xx < idx.width) & (yy >= 0)
        nb[hit, j] = idx.order[at[hit]]
    vec = uv[np.maximum(nb, 0)] - uv[centre][:, None, :]
    norm = np.linalg.norm(vec, axis=2)
    unit = vec / np.where(norm > 0, norm, 1.0)[..., None]
    cos = np.einsum("mik,mjk->mij", unit, unit)
    have = (nb >= 0) & (norm > 0)
    cos = np.where(have[:, :, None] & have[:, None, :], cos, np.inf)
    best = cos.reshape(centre.size, -1).argmin(axis=1)
    ia, ib = np.divmod(best, len(offsets))
    rows = np.arange(centre.size)
    use = cos[rows, ia, ib] <= -0.5
    return centre[use], nb[rows, ia][use], nb[rows, ib][use]


def _wide_checks(uv: np.ndarray, idx: _RingIndex, centre: np.ndarray, max_lag: int) -> list:
    """The checks wider than 1 px (``NEIGHBOUR_LAGS`` up to ``max_lag``), each (lag, checked samples (m,),
    their four same-ring nodes (m, 4), the cubic's weights (m, 4)), for the lags where at
    least ``MIN_PAIRS`` samples have all four: every ``centre`` sample, with its ring's
    direction there from the ring's samples around it (a ring broken up by dropped
    samples still has one)."""
    wide, direction = _ring_directions(uv, idx.ring, idx.at_pixel, idx.width, centre)
    out = []
    for lag in (k for k in NEIGHBOUR_LAGS[1:] if k <= max_lag):
        nodes, place = _lag_nodes(uv, idx.ring, idx.at_pixel, idx.width, wide, direction, lag)
        fine = ((nodes >= 0).all(axis=1) & (np.diff(place, axis=1) > 0).all(axis=1) & (place[:, 1] < 0)
                & (place[:, 2] > 0))
        if np.count_nonzero(fine) >= MIN_PAIRS:
            out.append((lag, wide[fine], nodes[fine], _lagrange_at_zero(place[fine])))
    return out


def _check_variance(u, cc, nodes, w, x, y, window):
    """Var(e_c - sum_i w_i e_i) per checked sample ``cc`` (m,) against its ``nodes`` (m, k)
    with weights ``w`` (m, k), for errors of standard deviations ``u`` (n,) that pixels
    (``x``, ``y``) share as far as their ``window`` x ``window`` means overlap."""
    def overlap(i, j):  # the share of error two pixels have in common under a window x window mean
        return (np.maximum(window - np.abs(x[i] - x[j]), 0) * np.maximum(window - np.abs(y[i] - y[j]), 0)
                / float(window * window))

    v = u[cc] ** 2 + np.einsum("ij,ij->i", w ** 2, u[nodes] ** 2)
    if window > 1:
        for i in range(nodes.shape[1]):
            v = v - 2 * w[:, i] * overlap(cc, nodes[:, i]) * u[cc] * u[nodes[:, i]]
            for j in range(i + 1, nodes.shape[1]):
                v = v + 2 * w[:, i] * w[:, j] * overlap(nodes[:, i], nodes[:, j]) * u[nodes[:, i]] * u[nodes[:, j]]
    return v


def fit_neighbour_model(depth: np.ndarray, s: np.ndarray, sigma_px: np.ndarray, pixel: np.ndarray,
                        ring: np.ndarray | None, uv: np.ndarray, *, width: int, window: int = 1,
                        group: np.ndarray | None = None, max_samples: int = MAX_CHECK_SAMPLES,
                        reach: np.ndarray | None = None) -> ErrorModel:
    """The ring coordinate's missed error terms where no angle checks it: from each
    sample's disagreement with its neighbours on the same ring (or, for a dense code,
    the neighbouring pixels).

    A smooth surface's depth along a ring's samples (one a camera pixel) is a straight
    line over three of them to far below the decode's errors (a 20 mm radius bends it by
    ~h^2 / R, ~5e-4 mm over 0.1 mm steps), while each sample's error comes from its
    own camera pixels: r = d - ((1 - t) d_a + t d_b), with a and b the neighbours on
    either side and t the sample's place between them, has the variance
    V + (1 - t)^2 V_a + t^2 V_b. Wider checks (``NEIGHBOUR_LAGS``) put a cubic through
    four neighbours instead (r = d - sum w_i d_i, variance V + sum w_i^2 V_i): they see
    the errors that neighbouring pixels share. Each check is fitted as the pairs of
    :func:`fit_error_model` are, with two terms: k (on the predicted depth sigma s) and a
    floor in projector px; the widest check that finds ``MIN_PAIRS`` samples is kept.
    What is smooth along a ring over more than the widest check (a blurred edge's bias)
    is not seen: that needs the angle.

    Args:
        depth: (n,) each sample's depth along its camera ray (mm), NaN where not placed.
        s: (n,) its predicted standard deviation (mm).
        sigma_px: (n,) the decode's predicted standard deviation of rho (projector px).
        pixel: (n,) linear camera pixel y * width + x of each sample.
        ring: (n,) ring index of each sample, or None for a dense code (one sample a pixel).
        uv: (n, 2) the samples' camera positions (px).
        width: camera width (px).
        window: the side (px) of the square a dense decode averages each pixel over
            (2 r + 1 for a smoothing radius r; 1: none): neighbouring pixels then share
            part of their errors (a box's overlap), which their difference would hide.
        group: (n,) int, or None: the codec's groups of samples that err differently
            (``Codec.error_groups``; -1: none); each group with enough checked samples
            gets a variance factor of its own (``groups``; a check's samples share a ring,
            so one group).
        max_samples: at most this many samples are checked (whole rows of them, evenly spread).
        reach: (n,) each sample's widest check (:func:`check_reach`), or None: with a ring,
            the samples the kept check does not reach get a variance factor per reach
            (``reach``: [[reach, factor, checks], ...], :func:`reach_scale`).

    Returns:
        :class:`ErrorModel` with k_rho and floor_rho_px (the other terms 1 and 0),
        ``pairs`` = samples the kept check used, ``lag_px`` its spacing;
        :func:`identity_model` with fewer than ``MIN_PAIRS``.

    Size: one argument per per-sample quantity (each (n,)) and the camera's and the
    decode's two facts (width, window) the checks need.
    """
    d, s, p = (np.asarray(x, np.float64) for x in (depth, s, sigma_px))
    uv = np.asarray(uv, np.float64).reshape(-1, 2)
    pixel = np.asarray(pixel, np.int64)
    max_lag = DENSE_MAX_LAG_PX if ring is None else NEIGHBOUR_LAGS[-1]
    ring = np.zeros(pixel.size, np.int64) if ring is None else np.asarray(ring, np.int64)
    ok = np.isfinite(d) & np.isfinite(s) & (s > 0) & np.isfinite(p) & (p > 0) & np.isfinite(uv).all(axis=1)
    n_ok = int(np.count_nonzero(ok))
    if n_ok < MIN_PAIRS:
        return identity_model(0)
    idx = _ring_index(ring, pixel, np.flatnonzero(ok), width)
    # every R-th row's samples are checked, against any samples of theirs on the same ring
    period = max(3, int(np.ceil(n_ok / max_samples)))
    centre = idx.order[(idx.y[idx.order] % period) == 1]
    c, a, b = _next_neighbours(uv, idx, centre)
    if c.size < MIN_PAIRS:
        return identity_model(int(c.size))
    ab = uv[b] - uv[a]
    t = np.clip(np.einsum("ij,ij->i", uv[c] - uv[a], ab) / np.einsum("ij,ij->i", ab, ab), 0.0, 1.0)
    g = s / p  # depth per projector px of rho
    checks = [(1, c, np.stack([a, b], 1), np.stack([1.0 - t, t], 1))] + _wide_checks(uv, idx, centre, max_lag)
    # the widest check that could be made: 1 px apart, neighbours share errors (a blur, a
    # smoothing window: it reads low) or alternate (a sharp projector's staircase: it reads
    # high); from ~3 px on the reading stays level (docs/accuracy.md)
    def residuals(check):
        _, cc, nodes, w = check
        r = d[cc] - np.einsum("ij,ij->i", w, d[nodes])
        return cc, r, np.stack([_check_variance(u, cc, nodes, w, idx.x, idx.y, window) for u in (s, g)], axis=1)

    lag = checks[-1][0]
    cc, r, X = residuals(checks[-1])
    q = _fit_variances(X, r * r, np.array([1.0, 0.0]))
    grp = (lambda at: np.asarray(group)[at]) if group is not None else (lambda at: None)
    groups = _group_scales(r * r, X @ q, grp(cc)) if group is not None else []
    gs = group_scale(groups, grp(cc))
    # a part of the view (an object's facets) from the checks that fit in it: at most REGION_MAX_LAG_PX wide
    rc, rr, rX = residuals([ch for ch in checks if ch[0] <= REGION_MAX_LAG_PX][-1])
    regions = _region_scales(rr * rr, rX @ q * group_scale(groups, grp(rc)), uv[rc])
    reach_scales = []
    if reach is not None and window == 1:
        var = ((q[0] * s * s + q[1] * g * g) * group_scale(groups, None if group is None else np.asarray(group))
               * region_scale(regions, uv))
        reach_scales = _reach_scales(d, var, uv, idx, np.asarray(reach, np.int64), lag)
    pairs, z0 = cc.size, np.abs(r) / np.sqrt(X[:, 0])
    z1 = np.abs(r) / np.sqrt(X @ q * gs * region_scale(regions, uv[cc]))
    return ErrorModel(k_rho=float(np.sqrt(max(q[0], 1.0))), k_tan=1.0, floor_rho_px=float(np.sqrt(q[1])),
                      floor_tan_px=0.0, floor_px=0.0, pairs=int(pairs), measured_by="neighbours", regions=regions,
                      groups=groups, reach=reach_scales,
                      indirect_rho_px=0.0, indirect_tan_px=0.0,
                      lag_px=int(lag), z_median=float(np.median(z0)), beyond_3=float(np.mean(z0 > 3)),
                      z_median_fitted=float(np.median(z1)), beyond_3_fitted=float(np.mean(z1 > 3)))


CROSS_RADII_PX = (8, 12, 16)
"""Radii (camera px) of the cross-ring check (``_cross_ring_checks``): for each reach class the
first at which it gets ``MIN_REACH_CHECKS`` checks, and the checked samples are checked at the
same radius for its factor. The samples of other rings within it fit a
quadratic of depth over the image, which wants three rings. On the default rig (rings ~3 px
apart in the image) 8 px holds two to either side; rings farther apart take a wider one (a
surface's shape then weighs more in the check); beyond 16 px, no reach factor is fitted."""
CROSS_REJECT = 4.0
"""A neighbour farther off the first fit than this many times the fit's robust spread (and its
own sigma) is left out of the second: another surface across an edge."""
CROSS_GATE = 3.0
"""A check whose neighbours spread more than this many of their sigmas (robustly) about their
own fit is not made: the neighbourhood is no smooth surface (an edge, a fold), and the check
would read its shape as error (on Spot, factors of thousands without this test)."""
MAX_REACH_CHECKS = 2000
"""Samples of each reach class checked across rings (evenly spread): a variance factor
to ~5 %."""
MIN_REACH_CHECKS = 100
"""Fewer cross-ring checks in a reach class (or among the reference samples) than this:
no factor for it (100 fix a variance factor to ~15 %; a factor is never below 1)."""


def check_reach(depth: np.ndarray, pixel: np.ndarray, ring: np.ndarray, uv: np.ndarray, *, width: int) -> np.ndarray:
    """(n,) int: each sample's widest check along its ring (:func:`fit_neighbour_model`):
    the largest of ``NEIGHBOUR_LAGS`` at which it has its four same-ring nodes (1: only its
    two next neighbours; 0: not even those: a fragment of a ring, an object's edge), -1
    where its depth is not finite."""
    d = np.asarray(depth, np.float64)
    uv = np.asarray(uv, np.float64).reshape(-1, 2)
    pixel = np.asarray(pixel, np.int64)
    ring = np.asarray(ring, np.int64)
    ok = np.isfinite(d) & np.isfinite(uv).all(axis=1)
    reach = np.where(ok, 0, -1)
    usable = np.flatnonzero(ok)
    if usable.size == 0:
        return reach
    idx = _ring_index(ring, pixel, usable, width)
    c, _, _ = _next_neighbours(uv, idx, idx.order)
    reach[c] = 1
    wide, direction = _ring_directions(uv, idx.ring, idx.at_pixel, idx.width, idx.order)
    for lag in NEIGHBOUR_LAGS[1:]:
        nodes, place = _lag_nodes(uv, idx.ring, idx.at_pixel, idx.width, wide, direction, lag)
        fine = ((nodes >= 0).all(axis=1) & (np.diff(place, axis=1) > 0).all(axis=1) & (place[:, 1] < 0)
                & (place[:, 2] > 0))
        reach[wide[fine]] = lag
    return reach


def _cross_ring_checks(d: np.ndarray, var: np.ndarray, uv: np.ndarray, idx: _RingIndex,
                       centre: np.ndarray, radius: int, chunk: int = 1024) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(checked samples (m,), r (m,), its predicted variance (m,)): each ``centre`` sample's depth
    against the quadratic of depth over the image that the samples of other rings within
    ``radius`` px fit (weighted by 1 / ``var``; refitted without the neighbours beyond
    ``CROSS_REJECT``), read at the sample's own position. Made where samples of an inner and an
    outer ring and of three rings in all surround the centre (the fit interpolates), at least
    three per term, and their own spread about the fit is within ``CROSS_GATE``. Unlike a check
    along the ring it reads the error along the ray itself: a ring sample's error moves it
    across its ring, and neighbours on its own ring see only the ring surface's share of the
    depth change (0.85 of the error on the far faint plane)."""
    height = idx.at_pixel.size // idx.width
    rad = int(radius)
    off = np.array([(dx, dy) for dy in range(-rad, rad + 1) for dx in range(-rad, rad + 1)
                    if 0 < dx * dx + dy * dy <= rad * rad])
    out_c, out_r, out_v = [], [], []
    for i0 in range(0, centre.size, chunk):
        c = centre[i0:i0 + chunk]
        m = c.size
        xx, yy = idx.x[c][:, None] + off[:, 0], idx.y[c][:, None] + off[:, 1]
        inside = (xx >= 0) & (xx < idx.width) & (yy >= 0) & (yy < height)
        j = np.where(inside, idx.at_pixel[np.where(inside, yy * idx.width + xx, 0)], -1)
        jj = np.maximum(j, 0)
        kc = idx.ring[c][:, None]
        have = (j >= 0) & (idx.ring[jj] != kc) & np.isfinite(d[jj]) & (var[jj] > 0)
        du, dv = uv[jj, 0] - uv[c, 0][:, None], uv[jj, 1] - uv[c, 1][:, None]
        A = np.stack([np.ones_like(du), du, dv, du * du, du * dv, dv * dv], -1)
        p = A.shape[-1]
        dj = np.where(have, d[jj], 0.0)
        rk = np.where(have, idx.ring[jj], np.iinfo(np.int64).max)
        srt = np.sort(rk, axis=1)
        rings = np.count_nonzero((np.diff(srt, axis=1) != 0) & (srt[:, 1:] != np.iinfo(np.int64).max), axis=1) + (
            srt[:, 0] != np.iinfo(np.int64).max)
        good = ((have & (idx.ring[jj] < kc)).any(axis=1) & (have & (idx.ring[jj] > kc)).any(axis=1) & (rings >= 3))
        sw = np.sqrt(np.where(have, 1.0 / np.where(have, var[jj], 1.0), 0.0))
        for it in range(2):
            w = np.where(have, sw * sw, 0.0)
            good &= np.count_nonzero(have, axis=1) >= 3 * p
            Aw = A * w[..., None]
            N = np.matmul(Aw.transpose(0, 2, 1), A)
            good &= np.linalg.cond(np.where(good[:, None, None], N, np.eye(p))) < 1e12  # six terms fixed
            Ns = np.where(good[:, None, None], N, np.eye(p))
            beta = np.linalg.solve(Ns, np.matmul(Aw.transpose(0, 2, 1), dj[..., None]))
            zr = np.where(have, np.abs(dj - np.matmul(A, beta)[..., 0]) * sw, np.inf)
            cnt = np.count_nonzero(have, axis=1)
            srt_z = np.sort(zr, axis=1)  # each row's neighbours first, the missing (inf) last
            mid = np.maximum(cnt - 1, 0)
            spread = 0.5 * (srt_z[np.arange(m), mid // 2] + srt_z[np.arange(m), (mid + 1) // 2]) / 0.6745
            if it == 0:
                have &= ~(zr > CROSS_REJECT * np.maximum(spread, 1.0)[:, None])
        good &= spread <= CROSS_GATE
        b = np.linalg.solve(Ns, np.tile(np.eye(p)[0], (m, 1))[..., None])[..., 0]
        wi = np.where(have, sw * sw, 0.0) * np.matmul(A, b[..., None])[..., 0]
        fitted = (wi * dj).sum(axis=1)
        v = (wi * wi * np.where(have, var[jj], 0.0)).sum(axis=1)
        out_c.append(c[good])
        out_r.append(d[c[good]] - fitted[good])
        out_v.append(var[c[good]] + v[good])
    if not out_c:
        return np.zeros(0, np.int64), np.zeros(0), np.zeros(0)
    return np.concatenate(out_c), np.concatenate(out_r), np.concatenate(out_v)


def _reach_scales(d: np.ndarray, var: np.ndarray, uv: np.ndarray, idx: _RingIndex, reach: np.ndarray,
                  lag: int) -> list:
    """Samples that no check of ``lag`` px along their ring reaches (``check_reach`` < lag: a
    ring's fragments, an object's edges and grazing facets) err more than the checked ones
    the fit saw (ringscan's renderer: Spot's 1 % without a neighbour 34 % beyond 3 sigma,
    the far faint plane's half 11 %): per reach class, the variance factor of its cross-ring
    checks (:func:`_cross_ring_checks`, ``var``: the fitted model's variances) over the
    checked samples' (>= 1; a curved surface's departure from the check's plane is in both).
    Returns [[reach, factor, checks], ...]."""
    usable = idx.order
    ref = usable[reach[usable] >= lag]
    out = []
    classes = [k for k in np.unique(reach[usable]) if 0 <= k < lag]
    if not classes or ref.size == 0:
        return out

    def scale(cands, radius):
        c, r, v = _cross_ring_checks(d, var, uv, idx, cands[sample_subset(cands.size, MAX_REACH_CHECKS)], radius)
        return (_t_scale(r * r / (T_SCALE * T_SCALE * v)), c.size) if c.size >= MIN_REACH_CHECKS else (None, c.size)

    refs = {}
    for k in classes:
        for radius in CROSS_RADII_PX:  # the same radius for the class and the checked samples it is set against
            m_k, n = scale(usable[reach[usable] == k], radius)
            if m_k is None:
                continue
            if radius not in refs:
                refs[radius] = scale(ref, radius)[0]
            if refs[radius] is not None:
                out.append([int(k), round(float(np.clip(m_k / refs[radius], 1.0, GROUP_SCALE_RANGE[1])), 4), int(n)])
            break
    return out


def reach_scale(scales: list | None, reach: np.ndarray | None) -> np.ndarray | float:
    """Each sample's variance factor from :func:`_reach_scales` (as :func:`group_scale`: 1 where none)."""
    return group_scale([[k, m] for k, m, _ in scales] if scales else None, reach)


def widen_depth_sigma(s: np.ndarray, sigma_px: np.ndarray, model: ErrorModel) -> np.ndarray:
    """(n,) float32: a ring-only point's depth sigma s (mm) with ``model``'s terms:
    sqrt(k^2 s^2 + (floor * s / sigma_px)^2), the same as triangulating with
    :func:`apply_error_model`'s rho sigma (the depth's sigma is linear in rho's)."""
    s64 = np.asarray(s, np.float64)
    p = np.asarray(sigma_px, np.float64)
    g = np.where(p > 0, s64 / np.where(p > 0, p, 1.0), 0.0)
    return np.sqrt((model["k_rho"] * s64) ** 2 + (model["floor_rho_px"] * g) ** 2).astype(np.float32)


def widen_for_indirect(widened: np.ndarray, s: np.ndarray, sigma_px: np.ndarray, indirect: np.ndarray,
                       px: float) -> np.ndarray:
    """(n,) float32: ring-only depth sigmas ``widened`` (mm) with each sample's indirect-light
    share above the view's median (``indirect``: ``Samples.indirect``) moving its rho by
    ``px`` projector px per unit share, added in quadrature (through s / sigma_px, the
    depth per projector px). A share at or below the view's median adds nothing."""
    b = np.asarray(indirect, np.float64)
    b = np.maximum(b - np.median(b), 0.0) * px if b.size else b
    p = np.asarray(sigma_px, np.float64)
    g = np.where(p > 0, np.asarray(s, np.float64) / np.where(p > 0, p, 1.0), 0.0)
    return np.sqrt(np.asarray(widened, np.float64) ** 2 + (b * g) ** 2).astype(np.float32)


def _fit_variances(X: np.ndarray, d2: np.ndarray, lower: np.ndarray, upper: np.ndarray | None = None) -> np.ndarray:
    """The variances P (>= ``lower``, <= ``upper`` where given: equal bounds fix a term)
    of the model var_i = X_i @ P that fit the squared differences ``d2`` (n,) best under
    a Student-t of ``T_DOF`` degrees of freedom read back as Gaussian variances
    (``T_SCALE``). X: (n, m) each term's variance per unit."""
    n = d2.size
    # in units where every column's and the squared differences' medians are 1:
    # var = Xs @ q with q = P * col / d2_scale
    col = np.median(X, axis=0)
    col[col <= 0] = 1.0
    d2_scale = max(float(np.median(d2)), 1e-300)
    Xs = X / col
    d2 = d2 / d2_scale
    lower = lower * col / d2_scale
    bounds = [(lo, None) for lo in lower]
    if upper is not None:
        hi = np.asarray(upper, np.float64) * col / d2_scale
        bounds = [(lo, h if np.isfinite(h) else None) for lo, h in zip(lower, hi)]

    def nll(q):
        var = np.maximum(T_SCALE * T_SCALE * (Xs @ q), 1e-300)
        u = d2 / (T_DOF * var)
        f = 0.5 * np.sum(np.log(var)) + 0.5 * (T_DOF + 1) * np.sum(np.log1p(u))
        g_var = 0.5 / var - 0.5 * (T_DOF + 1) * u / (var * (1 + u))
        return f / n, T_SCALE * T_SCALE * (Xs.T @ g_var) / n

    from scipy.optimize import minimize  # here, not at import: SciPy's optimisers cost every command 0.3 s of start-up

    start = np.array([lo + 0.2 if h is None else 0.5 * (lo + h) for lo, h in bounds])
    res = minimize(nll, start, jac=True, method="L-BFGS-B", bounds=bounds,
                   options={"maxiter": 1000, "ftol": 1e-12, "gtol": 1e-9})
    return np.maximum(res.x, lower) * d2_scale / col


def _smooth_part(r: np.ndarray, uv: np.ndarray) -> tuple[np.ndarray, float]:
    """Each sample's share of the residual field that is smooth over ``TILE_PX``
    camera tiles (the median of its tile's signed residuals, 0 in tiles of fewer than
    ``MIN_TILE`` samples), and that field's variance less what its medians' own noise
    gives (>= 0)."""
    key = np.floor(uv / TILE_PX).astype(np.int64)
    tile = key[:, 0] * 1_000_003 + key[:, 1]
    _, inv, counts = np.unique(tile, return_inverse=True, return_counts=True)
    order = np.argsort(inv, kind="stable")
    starts = np.r_[0, np.cumsum(counts)[:-1]]
    med = np.zeros(counts.size)
    noise = np.zeros(counts.size)
    rs = r[order]
    for t in np.flatnonzero(counts >= MIN_TILE):
        x = rs[starts[t]:starts[t] + counts[t]]
        med[t] = np.median(x)
        mad = np.median(np.abs(x - med[t])) / 0.6745
        noise[t] = 1.571 * mad * mad / counts[t]  # a median's variance, pi / 2 sigma^2 / n
    field = med[inv]
    used = counts[inv] >= MIN_TILE
    if not used.any():
        return field, 0.0
    return field, max(float(np.mean(field[used] ** 2) - np.mean(noise[inv][used])), 0.0)


def apply_error_model(sigma_px: np.ndarray, k: float, floor_px: float, *, indirect_px: float = 0.0,
                      indirect: np.ndarray | None = None) -> np.ndarray:
    """sqrt(k^2 sigma^2 + floor^2 + (indirect_px * indirect)^2), float32 (``indirect``:
    (n,) each sample's indirect-light share above the view's, :func:`fit_error_model`)."""
    s = np.asarray(sigma_px, np.float64)
    var = (k * s) ** 2 + floor_px ** 2
    if indirect_px > 0 and indirect is not None:
        var = var + (indirect_px * np.asarray(indirect, np.float64)) ** 2
    return np.sqrt(var).astype(np.float32)
