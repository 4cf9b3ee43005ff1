"""Without the angle: each ring sample's predicted error checked against its neighbours on
the same ring (docs/reconstruction.md, "Honest sigma", "Without an angle").

A ring-only point (``--constraint rings``, or a pattern with no angle code) has no second
coordinate to check it; its neighbours along its ring do: a smooth surface's depth follows
a cubic through samples a few pixels apart to far below the decode's errors, so each
sample's departure from the cubic through its neighbours measures the error terms the
decode's model misses (:func:`fit_neighbour_model`: the same Student-t fit of the variances
as :func:`~ringscan.pipeline.reconstruct.error_scale.fit_error_model`). The samples no check
along their ring reaches (broken rings, a silhouette's fragments) get a factor per reach class
from checks across rings (:func:`check_reach`, ``_cross_ring_checks``, ``_reach_scales``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import warp as wp

from ringscan.kernels.compact import pixel_rows
from ringscan.pipeline.reconstruct.error_scale import (
    GROUP_SCALE_RANGE,
    MAX_CHECK_SAMPLES,
    MIN_PAIRS,
    T_SCALE,
    ErrorModel,
    _fit_variances,
    _group_scales,
    _region_scales,
    _t_scale,
    group_scale,
    identity_model,
    region_scale,
    sample_subset,
)

__all__ = ["NEIGHBOUR_LAGS", "fit_neighbour_model", "check_reach", "reach_scale", "widen_depth_sigma",
           "widen_for_indirect", "widen_for_shading"]

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


def _wide_checks(uv: np.ndarray, idx: _RingIndex, centre: np.ndarray, max_lag: int, device="cpu") -> list:
    """The checks wider than 1 px (``NEIGHBOUR_LAGS`` up to ``max_lag``), each (lag, checked samples (m,),
    their four same-ring nodes (m, 4), the cubic's weights (m, 4)), for the lags where at
    least ``MIN_PAIRS`` samples have all four: every ``centre`` sample, with its ring's
    direction there from the ring's samples around it (a ring broken up by dropped
    samples still has one). The lags below ``REGION_MAX_LAG_PX`` only where none from it up
    to it holds (the model reads the widest check and the widest up to that one). ``device``: where the
    node search's kernels run."""
    lags = [k for k in NEIGHBOUR_LAGS[1:] if k <= max_lag]
    if not lags:
        return []

    from ringscan.kernels.ring_checks import pixel_offsets, ring_lag_nodes  # (the neighbour model's only)

    # where the usable samples lie in their pixels (the ones the pixel lookup holds among them)
    held = pixel_offsets(uv[idx.order], idx.y[idx.order] * idx.width + idx.x[idx.order], idx.width)

    def at(run):
        # the ring's direction at each centre and its nodes at each lag: kernels.ring_checks (the same samples
        # and places as _ring_directions and _lag_nodes state them in NumPy, ~30x faster)
        wide, _, nodes_at, place_at = ring_lag_nodes(uv, idx.ring, idx.at_pixel, centre, width=idx.width, lags=run,
                                                     offsets=held, device=device)
        out = {}
        for li, lag in enumerate(run):
            nodes, place = nodes_at[:, li], place_at[:, li]
            fine = ((nodes >= 0).all(axis=1) & (np.diff(place, axis=1) > 0).all(axis=1) & (place[:, 1] < 0)
                    & (place[:, 2] > 0))
            if np.count_nonzero(fine) >= MIN_PAIRS:
                out[lag] = (lag, wide[fine], nodes[fine], _lagrange_at_zero(place[fine]))
        return out

    # the model uses the widest check and the widest up to REGION_MAX_LAG_PX: the narrower ones are searched
    # only where that one finds too few samples (on a whole view a third of these searches saved)
    wider = tuple(k for k in lags if k >= REGION_MAX_LAG_PX)
    found = at(wider) if wider else {}
    if not any(k <= REGION_MAX_LAG_PX for k in found) and len(wider) < len(lags):
        found.update(at(tuple(k for k in lags if k < REGION_MAX_LAG_PX)))
    return [found[k] for k in lags if k in found]


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
                        reach: np.ndarray | None = None, device="cpu") -> ErrorModel:
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
        device: where the checks' kernels run (the view's device; the arrays here are NumPy,
            copied there for them and their results read back).

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
    # (the neighbour model's kernels load with it: a view with an angle code or two cameras never runs them)
    from ringscan.kernels.ring_checks import next_neighbours

    # every R-th row's samples are checked, against any samples of theirs on the same ring; a view too
    # small for MIN_PAIRS checks so has every sample checked (its checks then share samples: k is still
    # what they read, known a little less well than their count says) rather than none (the decode's
    # sigma as it is: on a small view of Mitsuba's corner 4x its errors)
    for period in dict.fromkeys((max(3, int(np.ceil(n_ok / max_samples))), 1)):
        centre = idx.order[(idx.y[idx.order] % period) == min(1, period - 1)]
        # (kernels.ring_checks.next_neighbours: _next_neighbours' samples, by a kernel)
        c, a, b = next_neighbours(uv, ring, pixel, idx.key, idx.order, idx.at_pixel, idx.npix, centre,
                                  width=width, device=device)
        if c.size >= MIN_PAIRS:
            break
    if c.size < MIN_PAIRS:
        return identity_model(int(c.size))
    ab = uv[b] - uv[a]
    t = np.clip(np.einsum("ij,ij->i", uv[c] - uv[a], ab) / np.einsum("ij,ij->i", ab, ab), 0.0, 1.0)
    g = s / p  # depth per projector px of rho
    checks = [(1, c, np.stack([a, b], 1), np.stack([1.0 - t, t], 1))] + _wide_checks(uv, idx, centre, max_lag,
                                                                                     device)
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
    for _ in range(CLIP_ROUNDS):
        # a check is five samples: one bad sample (a fringe's order, a pixel across an edge) spoils
        # five checks, and a quarter of them spoilt (a dense code at half size) read k twice what the
        # rest do; the core is fitted without the checks beyond CLIP_Z of the last fit (the tiles'
        # factors still see them)
        core = r * r <= CLIP_Z * CLIP_Z * (X @ q)
        if np.count_nonzero(~core) <= CLIP_SHARE * core.size or np.count_nonzero(core) < MIN_PAIRS:
            break  # a few far checks barely move the Student-t: no refit for them
        q = _fit_variances(X[core], (r * r)[core], np.array([1.0, 0.0]))
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
        reach_scales = _reach_scales(d, var, uv, idx, np.asarray(reach, np.int64), lag, device)
    pairs, z0 = cc.size, np.abs(r) / np.sqrt(X[:, 0])
    z1 = np.abs(r) / np.sqrt(X @ q * gs * region_scale(regions, uv[cc]))
    return ErrorModel(k_rho=float(np.sqrt(max(q[0], 1.0))), k_tan=1.0, floor_rho_px=float(np.sqrt(q[1])),
                      floor_tan_px=0.0, floor_px=0.0, pairs=int(pairs), measured_by="neighbours", regions=regions,
                      groups=groups, reach=reach_scales,
                      indirect_rho_px=0.0, indirect_tan_px=0.0,
                      lag_px=int(lag), z_median=float(np.median(z0)), beyond_3=float(np.mean(z0 > 3)),
                      z_median_fitted=float(np.median(z1)), beyond_3_fitted=float(np.mean(z1 > 3)))


CLIP_Z = 5.0
"""Checks farther off than this many of the fitted sigmas are left out of the next fit of the core
(``fit_neighbour_model``; a Gaussian leaves out 6e-7 of its own)."""
CLIP_ROUNDS = 3
"""Rounds of that fit."""
CLIP_SHARE = 0.01
"""At most this share of the checks beyond ``CLIP_Z``: the fit stands (a Student-t of 5 degrees of
freedom is moved little by them; each refit costs ~12 ms a full-size view on one core)."""


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
MAX_REACH_CHECKS = 1000
"""Samples of each reach class checked across rings (evenly spread): a variance factor to ~5 %
(``MIN_REACH_CHECKS``' 100 fix one to ~15 %). 2000 until 2026-12-07: a small view's fits then cost
more than the rest of its model, and the factors moved by less than their own spread."""
REF_PER_CHECK = 3
"""The checked samples a reach class is set against: this many for each of its own checks (at most
``MAX_REACH_CHECKS``): a small class's factor is no better known for a larger reference (a variance
ratio of n and 3 n checks: 1.15x the error of n alone), and a small view's fits cost."""
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


def _cross_fit(A: np.ndarray, dj: np.ndarray, have: np.ndarray, sw: np.ndarray,
               good: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """One weighted fit of :func:`_cross_ring_checks` a row: (the normal matrices, the identity where the
    fit cannot be made (m, p, p); ``good`` less those rows; each row's robust spread of its neighbours'
    normalised residuals (m,); those residuals (m, K), inf where no neighbour)."""
    m, p = A.shape[0], A.shape[-1]
    w = np.where(have, sw * sw, 0.0)
    good = good & (np.count_nonzero(have, axis=1) >= 3 * p)
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
    return Ns, good, spread, zr


def _cross_ring_checks(d: np.ndarray, var: np.ndarray, uv: np.ndarray, idx: _RingIndex,
                       centre: np.ndarray, radius: int, chunk: int = 256) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
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
        xx, yy = idx.x[c][:, None] + off[:, 0], idx.y[c][:, None] + off[:, 1]
        inside = (xx >= 0) & (xx < idx.width) & (yy >= 0) & (yy < height)
        j = np.where(inside, idx.at_pixel[np.where(inside, yy * idx.width + xx, 0)], -1)
        jj = np.maximum(j, 0)
        kc = idx.ring[c][:, None]
        have = (j >= 0) & (idx.ring[jj] != kc) & np.isfinite(d[jj]) & (var[jj] > 0)
        rk = np.where(have, idx.ring[jj], np.iinfo(np.int64).max)
        srt = np.sort(rk, axis=1)
        rings = np.count_nonzero((np.diff(srt, axis=1) != 0) & (srt[:, 1:] != np.iinfo(np.int64).max), axis=1) + (
            srt[:, 0] != np.iinfo(np.int64).max)
        good = ((have & (idx.ring[jj] < kc)).any(axis=1) & (have & (idx.ring[jj] > kc)).any(axis=1) & (rings >= 3))
        # the fits only where a check can be made (each row's numbers are its own)
        c, jj, have, good = c[good], jj[good], have[good], good[good]
        m = c.size
        du, dv = uv[jj, 0] - uv[c, 0][:, None], uv[jj, 1] - uv[c, 1][:, None]
        A = np.stack([np.ones_like(du), du, dv, du * du, du * dv, dv * dv], -1)
        p = A.shape[-1]
        dj = np.where(have, d[jj], 0.0)
        sw = np.sqrt(np.where(have, 1.0 / np.where(have, var[jj], 1.0), 0.0))
        Ns, good, spread, zr = _cross_fit(A, dj, have, sw, good)
        # refitted without the neighbours far off the first fit: only the rows that lose one (the others'
        # second fit is their first, to the bit)
        far = have & (zr > CROSS_REJECT * np.maximum(spread, 1.0)[:, None])
        redo = np.flatnonzero(far.any(axis=1))
        if redo.size:
            have[redo] &= ~far[redo]
            Ns[redo], good[redo], spread[redo], _ = _cross_fit(A[redo], dj[redo], have[redo], sw[redo], good[redo])
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
                  lag: int, device="cpu") -> list:
    """Samples that no check of ``lag`` px along their ring reaches (``check_reach`` < lag: a
    ring's fragments, an object's edges and grazing facets) err more than the checked ones
    the fit saw (ringscan's renderer: Spot's 1 % without a neighbour 34 % beyond 3 sigma,
    the far faint plane's half 11 %): per reach class, the variance factor of its cross-ring
    checks (:func:`_cross_ring_checks`, ``var``: the fitted model's variances) over the
    checked samples' (>= 1; a curved surface's departure from the check's plane is in both).
    ``device``: where the checks' kernel runs (the view's arrays copied there once). Returns [[reach,
    factor, checks], ...]."""
    usable = idx.order
    ref = usable[reach[usable] >= lag]
    out = []
    classes = [k for k in np.unique(reach[usable]) if 0 <= k < lag]
    if not classes or ref.size == 0:
        return out

    # the view's arrays for the kernel, made once (kernels.cross_checks.cross_ring_checks: the checks of
    # _cross_ring_checks, their numbers to rounding)
    # (on the view's device: the checks are the model's largest cost, and a GPU's to take)
    view = dict(depth=wp.array(np.ascontiguousarray(d, np.float64), dtype=wp.float64, device=device),
                var=wp.array(np.ascontiguousarray(var, np.float64), dtype=wp.float64, device=device),
                uv=wp.array(np.ascontiguousarray(uv, np.float64), dtype=wp.vec2d, device=device),
                ring=wp.array(idx.ring.astype(np.int32), dtype=wp.int32, device=device),
                pixel=wp.array((idx.y * idx.width + idx.x).astype(np.int32), dtype=wp.int32, device=device),
                at_pixel=wp.array(idx.at_pixel.astype(np.int32), dtype=wp.int32, device=device))
    view["rows"] = pixel_rows(view["at_pixel"], len(d))  # its pixels' samples row by row, once for every call

    def checks(cands, radius, most):
        from ringscan.kernels.cross_checks import cross_ring_checks  # (the neighbour model's only)
        c, r, v = cross_ring_checks(**view, centre=cands[sample_subset(cands.size, most)], radius=radius,
                                    width=idx.width, reject=CROSS_REJECT, gate=CROSS_GATE)
        return (_t_scale(r * r / (T_SCALE * T_SCALE * v)), c.size) if c.size >= MIN_REACH_CHECKS else (None, c.size)

    found = []  # (class, radius, its scale, its checks): the first radius that gives a class enough checks
    for k in classes:
        for radius in CROSS_RADII_PX:  # the same radius for the class and the checked samples it is set against
            m_k, n = checks(usable[reach[usable] == k], radius, MAX_REACH_CHECKS)
            if m_k is not None:
                found.append((k, radius, m_k, n))
                break
    refs = {}
    for radius in dict.fromkeys(f[1] for f in found):
        # the checked samples at that radius: REF_PER_CHECK times the largest class's checks (its own count
        # bounds the ratio's precision), at least MIN_REACH_CHECKS, at most MAX_REACH_CHECKS
        most = max(n for _, rad, _, n in found if rad == radius)
        refs[radius] = checks(ref, radius, int(np.clip(REF_PER_CHECK * most, MIN_REACH_CHECKS,
                                                       MAX_REACH_CHECKS)))[0]
    out = []
    for k, radius, m_k, n in found:
        if refs[radius] is not None:
            out.append([int(k), round(float(np.clip(m_k / refs[radius], 1.0, GROUP_SCALE_RANGE[1])), 4), int(n)])
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
    return _widen_by_shift(widened, s, sigma_px, np.maximum(b - np.median(b), 0.0) * px if b.size else b)


def widen_for_shading(widened: np.ndarray, s: np.ndarray, sigma_px: np.ndarray, shading: np.ndarray,
                      px: float) -> np.ndarray:
    """(n,) float32: ring-only depth sigmas ``widened`` (mm) with each sample's light gradient
    (``shading``: ``Samples.shading``, its relative gradient per camera px) moving its rho by
    ``px`` projector px per unit gradient, added in quadrature (through s / sigma_px)."""
    return _widen_by_shift(widened, s, sigma_px, np.asarray(shading, np.float64) * px)


def _widen_by_shift(widened: np.ndarray, s: np.ndarray, sigma_px: np.ndarray, shift_px: np.ndarray) -> np.ndarray:
    """sqrt(widened^2 + (shift_px s / sigma_px)^2), float32: a rho shift (projector px) in depth."""
    p = np.asarray(sigma_px, np.float64)
    g = np.where(p > 0, np.asarray(s, np.float64) / np.where(p > 0, p, 1.0), 0.0)
    return np.sqrt(np.asarray(widened, np.float64) ** 2 + (shift_px * g) ** 2).astype(np.float32)
