"""Two cameras, matching: a camera-1 sample finds its camera-2 position by equal
projector coordinate (docs/reconstruction.md "Two cameras", docs/design.md §19).

Each camera decodes the projector coordinate p = (u_p, v_p) of its samples; a
camera-1 sample (the query) is matched to the camera-2 position x2 where camera 2's
projector-coordinate field equals the query's p. Camera 2's samples (a dense
per-pixel map or scattered ring-edge samples: both are just (x2, p, sigma) triples
here) are binned by p into a grid of square cells (count, scan, write); each query
takes its ``k`` nearest samples in projector space (searching ring by ring of cells
out to a radius) and fits the local affine map x2 = x2m + A (p - pm) by weighted
least squares (weights 1 / sigma_p^2), evaluated at the query's p. Where the
neighbours lie on a line in projector space (ring edges: samples along one ring)
the map is fitted along that line only (pseudo-inverse), and the query must lie on
their curve (a quadratic through them: a ring edge is an arc). A neighbourhood that
straddles a depth discontinuity is one no single affine map fits: its fit residual
(camera px) or its gain (camera px per projector px) is too large, and the query is
dropped. No extrinsics are used, so the matches can re-estimate them; with
extrinsics, :func:`epipolar_distances` checks them against the epipolar lines.

The matches go on to :mod:`ringscan.kernels.stereo_rays` (triangulation of the two
or three rays). The matching has its own status codes (``MATCH_STATUS_NAMES``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import warp as wp

from ringscan.kernels.launch import check_array, default_threads, launch_spans, scan_counts
from ringscan.kernels.settings import LINE_RATIO, MAX_NEIGHBOURS, MatchSettings

wp.set_module_options({"enable_backward": False})  # no gradients are taken here: no adjoint code to compile

MAX_GRID_SPLIT = 4
"""Most halvings of ``MatchSettings.cell_px`` for a dense camera-2 map (:func:`match_by_projector`)."""
VecKi = wp.types.vector(length=MAX_NEIGHBOURS, dtype=wp.int32)
VecKf = wp.types.vector(length=MAX_NEIGHBOURS, dtype=wp.float32)

MATCH_OK = wp.constant(0)
MATCH_NO_COORDINATE = wp.constant(1)
MATCH_TOO_FEW = wp.constant(2)
MATCH_EXTRAPOLATED = wp.constant(3)
MATCH_DISCONTINUITY = wp.constant(4)
MATCH_STATUS_NAMES = ("ok", "no_coordinate", "too_few_neighbours", "extrapolated", "discontinuity")
SIGMA_FLOOR_PX = wp.constant(1.0e-3)
"""Least standard deviation (px) a sample or a ray is given: keeps the weights finite."""
MODEL_SHARE = wp.constant(0.5)
"""Share of one sample's excess scatter about the fitted map (its variance beyond the predicted
noise: the decode's model error) added to each camera's sigma: half each. Measured on the
virtual two-camera scan (benchmarks/stereo_rays.py, "Predicted match sigmas"): with it the
match errors over their predicted sigmas have a MAD of about 1 in each camera; without it 2."""
MAX_REFITS = wp.constant(1)
"""Neighbours a match may leave out, the worst-fitting first, before its neighbourhood counts as a
discontinuity: one misread code among eight does not lose the match."""
FIT_SIGMAS = wp.constant(3.0)
"""A neighbourhood is a discontinuity where its fit residual exceeds ``MatchSettings.max_fit_px``
and this many times the scatter its samples' own predicted sigmas leave (integer codes: a
projector pixel's quantisation, ~0.4 camera px at one camera pixel per projector pixel)."""

__all__ = [
    "MatchSettings",
    "Matches",
    "MATCH_STATUS_NAMES",
    "MAX_NEIGHBOURS",
    "SIGMA_FLOOR_PX",
    "projector_coordinates",
    "match_by_projector",
]


@wp.struct
class MatchParams:
    """The scalar settings of :func:`match_kernel`, filled once by :func:`match_by_projector`
    (the grid as binned, the rest from :class:`MatchSettings`)."""

    cell: wp.float32
    """The grid's cell size, projector px (``MatchSettings.cell_px``, split for a dense map)."""
    nx: wp.int32
    """The grid's columns."""
    ny: wp.int32
    """The grid's rows."""
    rings: wp.int32
    """Rings of cells the search reaches: ``MatchSettings.radius_px`` in cells."""
    k_max: wp.int32
    """``MatchSettings.neighbours``."""
    k_min: wp.int32
    """``MatchSettings.min_neighbours``."""
    line_ratio: wp.float32
    """``LINE_RATIO``."""
    max_offset: wp.float32
    """``MatchSettings.max_offset_px``."""
    max_extrapolation: wp.float32
    """``MatchSettings.max_extrapolation``."""
    max_fit: wp.float32
    """``MatchSettings.max_fit_px``."""
    max_gain: wp.float32
    """``MatchSettings.max_gain``."""
    maps: wp.int32
    """1: write ``proj_map`` and ``query_model`` (what three rays read); 0: they are one-element placeholders."""


@dataclass
class Matches:
    """Per query (Warp arrays of length n, the queries' device)."""

    uv2: wp.array
    """vec2 camera-2 pixel (distorted image) where the field equals the query's p; 0 where status != 0."""
    sigma2: wp.array
    """float32 predicted standard deviation of uv2 (camera-2 px, per axis): the camera-2
    samples' noise through the fit, and half of one neighbour's excess scatter about
    the fit (``MODEL_SHARE``)."""
    sigma1: wp.array
    """float32 the query's own projector-coordinate noise as camera-1 px (its
    sigma times the fitted gain: both cameras see the surface at similar scales),
    and the other half of that excess scatter."""
    gain: wp.array
    """float32 fitted camera-2 px per projector px."""
    proj_map: wp.array
    """vec4 the fitted map's linear part A (row-major: d uv2 / d p, camera-2 px per projector px): how uv2
    moves with the query's projector point, so that an error of that point (which the projector's ray in a
    three-ray triangulation carries as well) moves uv2 by A times it; 0 where the neighbours lie on a line
    (ring edges: the map across the line is unknown) and where status != 0."""
    query_model: wp.array
    """float32 sigma1's second term alone: the query's half of that excess scatter (camera-2 px), what the
    query's projector point carries beyond its own sigma (over ``gain`` in projector px); 0 where status != 0."""
    fit_px: wp.array
    """float32 RMS residual of the neighbours' fit (camera-2 px)."""
    status: wp.array
    """int32 ``MATCH_STATUS_NAMES`` index."""


# ----------------------------------------------------------------------------- helpers


@wp.func
def cell_of(p: wp.vec2, cell: float, nx: int, ny: int):
    """Grid cell (cx, cy) of projector point p; (-1, -1) outside the grid (or NaN)."""
    fx = p[0] / cell
    fy = p[1] / cell
    if not (fx >= 0.0 and fy >= 0.0 and fx < float(nx) and fy < float(ny)):
        return wp.vec2i(-1, -1)
    return wp.vec2i(int(fx), int(fy))


@wp.func
def box_count(sat: wp.array(dtype=wp.int32), nx: int, ny: int, x0: int, y0: int, x1: int, y1: int):
    """Samples in the grid's cells x0..x1, y0..y1 (inclusive, clipped to the grid), from the summed-area
    table ``sat`` ((ny + 1) * (nx + 1): sat[y * (nx + 1) + x] counts the cells left of x and above y)."""
    a0 = wp.max(x0, 0)
    b0 = wp.max(y0, 0)
    a1 = wp.min(x1, nx - 1) + 1
    b1 = wp.min(y1, ny - 1) + 1
    if a0 >= a1 or b0 >= b1:
        return 0
    w = nx + 1
    return sat[b1 * w + a1] - sat[b0 * w + a1] - sat[b1 * w + a0] + sat[b0 * w + a0]


@wp.func
def key_less(da: float, sa: int, db: float, sb: int, items: wp.array(dtype=wp.int32)):
    """Whether the sample at grid place sa, at squared distance da, comes before the one at sb: distance
    first, the sample index (``items``) breaks ties, so the neighbour set is the same on every device (a
    cell's places are in atomic order on CUDA). Ties are rare: the index is read only for one."""
    return da < db or (da == db and items[sa] < items[sb])


@wp.func
def sym_eigen(C: wp.mat22):
    """Eigenvalues l1 >= l2 of a symmetric 2x2 matrix and the unit eigenvector of l1:
    (l1, l2, v1x, v1y)."""
    tr = C[0, 0] + C[1, 1]
    df = 0.5 * (C[0, 0] - C[1, 1])
    rt = wp.sqrt(df * df + C[0, 1] * C[0, 1])
    l1 = 0.5 * tr + rt
    l2 = 0.5 * tr - rt
    v1 = wp.vec2(1.0, 0.0)
    if rt > 0.0:
        v1 = wp.normalize(wp.vec2(C[0, 1], l1 - C[0, 0]))
        if wp.abs(C[0, 1]) < 1.0e-12 * (l1 + 1.0e-30):
            v1 = wp.where(C[0, 0] >= C[1, 1], wp.vec2(1.0, 0.0), wp.vec2(0.0, 1.0))
    return wp.vec4(l1, l2, v1[0], v1[1])


@wp.func
def curve_offset(proj2: wp.array(dtype=wp.vec2), sigma2: wp.array(dtype=wp.float32), ns: VecKi, n: int,
                 pm: wp.vec2, v1: wp.vec2, v2: wp.vec2, sq: float, aq: float):
    """How far (projector px) the query lies across the neighbours' curve: the
    neighbours' across-coordinate a = (p - pm).v2 fitted as a quadratic in the
    along-coordinate s = (p - pm).v1 (a ring edge is an arc: a straight line
    would leave its sagitta, 0.4 px over 8 px of a 20 px ring), evaluated at the
    query's (sq, aq). With fewer than 4 neighbours a straight line.

    Size: a @wp.func reads camera 2's arrays and the query's neighbour list directly (Warp functions take no
    tuples of arrays), plus the local frame (pm, v1, v2) and the query's coordinates in it that match_kernel has
    already computed.
    """
    M = wp.mat33(0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
    b = wp.vec3(0.0, 0.0, 0.0)
    for k in range(n):
        j = ns[k]
        sg = wp.max(sigma2[j], SIGMA_FLOOR_PX)
        w = 1.0 / (sg * sg)
        dp = proj2[j] - pm
        s = wp.dot(dp, v1)
        f = wp.vec3(1.0, s, wp.where(n >= 4, s * s, 0.0))
        M += w * wp.outer(f, f)
        b += w * wp.dot(dp, v2) * f
    if n < 4:
        M[2, 2] = 1.0
    if not (wp.abs(wp.determinant(M)) > 0.0):
        return 1.0e9
    c = wp.inverse(M) * b
    return aq - (c[0] + c[1] * sq + c[2] * sq * sq)


# ----------------------------------------------------------------------------- kernels


@wp.kernel
def polar_coordinates_kernel(
    rho: wp.array(dtype=wp.float32),
    phi: wp.array(dtype=wp.float32),
    sigma_rho: wp.array(dtype=wp.float32),
    sigma_tan: wp.array(dtype=wp.float32),
    center: wp.vec2,
    proj: wp.array(dtype=wp.vec2),
    sigma: wp.array(dtype=wp.float32),
):
    """p = c + rho (cos phi, sin phi) and its isotropic sigma sqrt((s_rho^2 + s_tan^2) / 2).

    rho, phi, sigma_rho, sigma_tan (n,) float32: read. proj (n,) vec2 (NaN where
    phi is NaN), sigma (n,) float32: written."""
    i = wp.tid()
    r = rho[i]
    f = phi[i]
    proj[i] = wp.vec2(center[0] + r * wp.cos(f), center[1] + r * wp.sin(f))
    sr = sigma_rho[i]
    st = sigma_tan[i]
    sigma[i] = wp.sqrt(0.5 * (sr * sr + st * st))


@wp.kernel
def count_cells_kernel(
    proj: wp.array(dtype=wp.vec2),
    cell: float,
    nx: int,
    ny: int,
    counts: wp.array(dtype=wp.int32),
):
    """counts[cy * nx + cx] += 1 for each sample's cell. proj (m,) read; counts (nx * ny,) written (zeroed first)."""
    j = wp.tid()
    c = cell_of(proj[j], cell, nx, ny)
    if c[0] >= 0:
        wp.atomic_add(counts, c[1] * nx + c[0], 1)


@wp.kernel
def write_cells_kernel(
    proj: wp.array(dtype=wp.vec2),
    cell: float,
    nx: int,
    ny: int,
    offsets: wp.array(dtype=wp.int32),
    cursor: wp.array(dtype=wp.int32),
    items: wp.array(dtype=wp.int32),
):
    """items[offsets[c] + k] = j for the samples of cell c (order within a cell
    arbitrary: the neighbour search sorts by distance and index). proj (m,),
    offsets (nx * ny,) read; cursor (nx * ny,) zeroed, items (binned,) written."""
    j = wp.tid()
    c = cell_of(proj[j], cell, nx, ny)
    if c[0] >= 0:
        ci = c[1] * nx + c[0]
        k = wp.atomic_add(cursor, ci, 1)
        items[offsets[ci] + k] = j


@wp.kernel
def gather_cells_kernel(
    items: wp.array(dtype=wp.int32),
    proj: wp.array(dtype=wp.vec2),
    uv: wp.array(dtype=wp.vec2),
    sigma: wp.array(dtype=wp.float32),
    proj_out: wp.array(dtype=wp.vec2),
    uv_out: wp.array(dtype=wp.vec2),
    sigma_out: wp.array(dtype=wp.float32),
):
    """Camera 2's samples in the grid's order: out[s] = in[items[s]] (a cell's samples side by side, so
    the neighbour search reads memory in runs, not scattered over the view). items (binned,) int32;
    proj, uv (m,) vec2, sigma (m,) float32: read. proj_out, uv_out (binned,) vec2, sigma_out
    (binned,) float32: written."""
    s = wp.tid()
    j = items[s]
    proj_out[s] = proj[j]
    uv_out[s] = uv[j]
    sigma_out[s] = sigma[j]


@wp.kernel
def sat_rows_kernel(counts: wp.array(dtype=wp.int32), nx: int, sat: wp.array(dtype=wp.int32)):
    """Row y + 1 of the summed-area table: the running sum of grid row y's counts (one thread a row).
    counts (ny * nx,) read; sat ((ny + 1) * (nx + 1),) zeroed, written."""
    y = wp.tid()
    acc = int(0)
    for x in range(nx):
        acc += counts[y * nx + x]
        sat[(y + 1) * (nx + 1) + x + 1] = acc


@wp.kernel
def sat_cols_kernel(ny: int, nx: int, sat: wp.array(dtype=wp.int32)):
    """The summed-area table's running sums down column x (one thread a column, after :func:`sat_rows_kernel`).
    sat ((ny + 1) * (nx + 1),) read and written."""
    x = wp.tid()
    for y in range(2, ny + 1):
        sat[y * (nx + 1) + x] = sat[y * (nx + 1) + x] + sat[(y - 1) * (nx + 1) + x]


@wp.kernel
def match_kernel(
    query: wp.array(dtype=wp.vec2),
    query_sigma: wp.array(dtype=wp.float32),
    proj2: wp.array(dtype=wp.vec2),
    uv2: wp.array(dtype=wp.vec2),
    sigma2: wp.array(dtype=wp.float32),
    offsets: wp.array(dtype=wp.int32),
    counts: wp.array(dtype=wp.int32),
    items: wp.array(dtype=wp.int32),
    sat: wp.array(dtype=wp.int32),
    params: MatchParams,
    i0: int,
    out_uv: wp.array(dtype=wp.vec2),
    out_sigma2: wp.array(dtype=wp.float32),
    out_sigma1: wp.array(dtype=wp.float32),
    out_gain: wp.array(dtype=wp.float32),
    out_map: wp.array(dtype=wp.vec4),
    out_query_model: wp.array(dtype=wp.float32),
    out_fit: wp.array(dtype=wp.float32),
    status: wp.array(dtype=wp.int32),
):
    """Match query i0 + tid.

    query (n,) vec2 projector px, query_sigma (n,) float32; proj2, uv2 (binned,) vec2,
    sigma2 (binned,) float32 (camera 2's samples in the grid's order, :func:`gather_cells_kernel`);
    offsets, counts (nx * ny,) int32, items (binned,) int32 (the grid: each place's sample index), sat
    ((ny + 1) * (nx + 1),) int32 (its summed-area table, :func:`box_count`): read. params: the grid and the fit's
    settings (:class:`MatchParams`). out_uv (n,) vec2, out_sigma2, out_sigma1,
    out_gain (n,) float32, out_map (n,) vec4, out_query_model, out_fit (n,) float32, status (n,) int32: written
    (:class:`Matches`; out_map and out_query_model only with ``params.maps``).

    Size: one thread per query, and the steps share its registers: the k-nearest search fills the fixed-size
    arrays nd/ns that the fit, its refits (a neighbour dropped from ns) and the variances then read, so the
    search and the fit stay one body. Warp kernels take each array as its own argument; the scalar settings
    already travel in MatchParams.
    """
    i = i0 + wp.tid()
    cell = params.cell
    nx = params.nx
    ny = params.ny
    rings = params.rings
    k_max = params.k_max
    k_min = params.k_min
    line_ratio = params.line_ratio
    max_offset = params.max_offset
    max_extrapolation = params.max_extrapolation
    max_fit = params.max_fit
    max_gain = params.max_gain
    q = query[i]
    out_uv[i] = wp.vec2(0.0, 0.0)
    out_sigma2[i] = 0.0
    out_sigma1[i] = 0.0
    out_gain[i] = 0.0
    maps = params.maps != 0
    if maps:
        out_map[i] = wp.vec4(0.0, 0.0, 0.0, 0.0)
        out_query_model[i] = 0.0
    out_fit[i] = -1.0
    if not (q[0] == q[0] and q[1] == q[1]):
        status[i] = MATCH_NO_COORDINATE
        return
    # the k nearest camera-2 samples within ``rings`` cells, sorted by (distance,
    # index)
    nd = VecKf()
    ns = VecKi()  # the neighbours' places in the grid's order, where the fit reads them
    n = int(0)
    r2max = float(rings) * cell * float(rings) * cell
    # what a sample's squared distance must not exceed to be a neighbour: the radius, then the k-th
    # nearest so far (a tie goes to the lower index: key_less)
    reach = r2max
    cx = int(wp.floor(q[0] / cell))
    cy = int(wp.floor(q[1] / cell))
    # q's distance to the edge of its own cell: rings 0 .. rr - 1 cover every sample within
    # (rr - 1) * cell + margin of q (the search stops as soon as the k-th nearest lies within)
    fx = q[0] - float(cx) * cell
    fy = q[1] - float(cy) * cell
    margin = wp.min(wp.min(fx, cell - fx), wp.min(fy, cell - fy))
    # the summed-area table skips what holds no sample (a query beside a gap in camera 2's view
    # would otherwise read every cell out to the radius): the whole square, a ring, a ring's row
    if box_count(sat, nx, ny, cx - rings, cy - rings, cx + rings, cy + rings) < k_min:
        status[i] = MATCH_TOO_FEW
        return
    inside = int(0)  # samples in rings 0 .. rr - 1
    for rr in range(rings + 1):
        covered = float(rr - 1) * cell + margin
        if rr > 0 and n == k_max and nd[k_max - 1] <= covered * covered:
            break
        square = box_count(sat, nx, ny, cx - rr, cy - rr, cx + rr, cy + rr)
        if square == inside:
            continue
        inside = square
        for gy in range(wp.max(cy - rr, 0), wp.min(cy + rr, ny - 1) + 1):
            # ring rr's cells: its top and bottom rows whole, the two end cells of the rows between
            edge = wp.abs(gy - cy) == rr
            if edge and box_count(sat, nx, ny, cx - rr, gy, cx + rr, gy) == 0:
                continue
            step = wp.where(edge, 1, wp.max(2 * rr, 1))
            # the cell's nearest point to q, as y then x: a cell farther than the k-th nearest so far
            # (or than the radius) holds no neighbour
            ey = wp.max(wp.max(float(gy) * cell - q[1], q[1] - float(gy + 1) * cell), 0.0)
            for gx in range(cx - rr, cx + rr + 1, step):
                ex = wp.max(wp.max(float(gx) * cell - q[0], q[0] - float(gx + 1) * cell), 0.0)
                if gx >= 0 and gx < nx and ex * ex + ey * ey <= reach:
                    ci = gy * nx + gx
                    for s in range(offsets[ci], offsets[ci] + counts[ci]):
                        dp = proj2[s] - q
                        d2 = wp.dot(dp, dp)
                        if d2 <= reach:
                            # an insertion into the sorted list: the larger keys shift up one place
                            pos = int(-1)
                            if n < k_max:
                                pos = n
                                n += 1
                            elif key_less(d2, s, nd[k_max - 1], ns[k_max - 1], items):
                                pos = k_max - 1
                            if pos >= 0:
                                while pos > 0 and key_less(d2, s, nd[pos - 1], ns[pos - 1], items):
                                    nd[pos] = nd[pos - 1]
                                    ns[pos] = ns[pos - 1]
                                    pos -= 1
                                nd[pos] = d2
                                ns[pos] = s
                                if n == k_max:
                                    reach = wp.min(nd[k_max - 1], r2max)
    if n < k_min:
        status[i] = MATCH_TOO_FEW
        return
    # One neighbour that no map through the others fits (a misread code) is left out and the
    # map fitted again; a neighbourhood that still does not fit straddles a depth edge.
    st = int(MATCH_DISCONTINUITY)
    for attempt in range(MAX_REFITS + 1):
        # weighted means, then the centred moments (projector: S; image x projector: B): the fit.
        # The plain (unweighted) mean and spread of the neighbours' projector points: the
        # neighbourhood's shape, which says whether the query lies among them and whether they
        # lie on a line. Judged on the weighted spread instead, a few precise neighbours among
        # imprecise ones (sub-pixel positions among integer codes: weights 100 times apart) would
        # leave the others no say, and a query amid its neighbours would look extrapolated.
        sw = float(0.0)
        pm = wp.vec2(0.0, 0.0)
        xm = wp.vec2(0.0, 0.0)
        pu = wp.vec2(0.0, 0.0)
        var_sum = float(0.0)
        for a in range(n):
            j = ns[a]
            sg = wp.max(sigma2[j], SIGMA_FLOOR_PX)
            w = 1.0 / (sg * sg)
            sw += w
            pm += w * proj2[j]
            xm += w * uv2[j]
            pu += proj2[j]
            var_sum += sg * sg
        pm = pm / sw
        xm = xm / sw
        pu = pu / float(n)
        S = wp.mat22(0.0, 0.0, 0.0, 0.0)
        B = wp.mat22(0.0, 0.0, 0.0, 0.0)
        Cu = wp.mat22(0.0, 0.0, 0.0, 0.0)
        for a in range(n):
            j = ns[a]
            sg = wp.max(sigma2[j], SIGMA_FLOOR_PX)
            w = 1.0 / (sg * sg)
            dp = proj2[j] - pm
            dx = uv2[j] - xm
            S += w * wp.outer(dp, dp)
            B += w * wp.outer(dx, dp)
            du = proj2[j] - pu
            Cu += wp.outer(du, du)
        # eigen-decompositions of the projector spreads (symmetric 2x2)
        e = sym_eigen(S / sw)
        l1 = e[0]
        l2 = e[1]
        v1 = wp.vec2(e[2], e[3])
        v2 = wp.vec2(-v1[1], v1[0])
        eu = sym_eigen(Cu / float(n))
        lu1 = eu[0]
        lu2 = eu[1]
        vu1 = wp.vec2(eu[2], eu[3])
        vu2 = wp.vec2(-vu1[1], vu1[0])
        if not (l1 > 1.0e-12 and lu1 > 1.0e-12):
            st = MATCH_EXTRAPOLATED
            break
        dq = q - pm
        a1 = wp.dot(dq, v1)
        a2 = wp.dot(dq, v2)
        dqu = q - pu
        full = lu2 >= line_ratio * lu1 and n >= 3
        if wp.abs(wp.dot(dqu, vu1)) > max_extrapolation * wp.sqrt(lu1):
            st = MATCH_EXTRAPOLATED
            break
        if full:
            # (or a weighted spread with nothing across: the neighbours that weigh lie on a line)
            if wp.abs(wp.dot(dqu, vu2)) > max_extrapolation * wp.sqrt(lu2) or not (l2 > 1.0e-6 * l1):
                st = MATCH_EXTRAPOLATED
                break
        elif wp.abs(curve_offset(proj2, sigma2, ns, n, pm, v1, v2, a1, a2)) > max_offset:
            # the query is off the neighbours' curve: the map across it is unknown
            st = MATCH_EXTRAPOLATED
            break
        # S^+ (in the eigenbasis): both directions, or the line's alone
        Sp = wp.outer(v1, v1) / (l1 * sw)
        if full:
            Sp = Sp + wp.outer(v2, v2) / (l2 * sw)
        A = B * Sp
        x = xm + A * dq
        g2 = A[0, 0] * A[0, 0] + A[0, 1] * A[0, 1] + A[1, 0] * A[1, 0] + A[1, 1] * A[1, 1]
        gain = wp.where(full, wp.sqrt(0.5 * g2), wp.sqrt(g2))
        # residuals of the fit: a neighbourhood across a depth edge fits no one map
        chi = float(0.0)
        ss = float(0.0)
        worst = int(0)
        worst_r2 = float(-1.0)
        for a in range(n):
            j = ns[a]
            sg = wp.max(sigma2[j], SIGMA_FLOOR_PX)
            r = uv2[j] - (xm + A * (proj2[j] - pm))
            r2 = wp.dot(r, r)
            ss += r2
            chi += r2 / (sg * sg)
            if r2 > worst_r2:
                worst_r2 = r2
                worst = a
        fit = wp.sqrt(ss / float(n))
        out_fit[i] = fit
        out_gain[i] = gain
        npar = wp.where(full, 3, 2)
        # the scatter the neighbours' own precision leaves about the map (camera px, RMS over
        # both axes: their projector variance through the map, less the parameters' share):
        # integer codes leave ~0.4 px at one camera px per projector px, sub-pixel ones a few
        # hundredths, under max_fit
        noise_fit = wp.sqrt(g2 * var_sum / float(n) * float(wp.max(n - npar, 0)) / float(n))
        if fit > wp.max(max_fit, FIT_SIGMAS * noise_fit) or gain > max_gain:
            if attempt < MAX_REFITS and n > k_min and n > 3:
                # the worst-fitting neighbour out (the last one in its place), and fit again
                ns[worst] = ns[n - 1]
                n -= 1
                continue
            st = MATCH_DISCONTINUITY
            break
        # the intercept's variance: the samples' projector noise through the map
        # (gain^2 sigma^2), scaled up by the fit's own scatter where that is larger
        scale = float(1.0)
        model2 = float(0.0)
        if n > npar and gain > 0.0:
            scale = wp.max(1.0, chi / (2.0 * float(n - npar) * gain * gain))
            # one sample's scatter about the map (per axis) beyond its predicted noise
            # (gain^2 times the neighbours' harmonic-mean variance n / sw): the decode's
            # model error, smooth along an edge, so the fit does not average it out of
            # uv2, and the query carries its own of the same size (design.md §19)
            model2 = wp.max(0.0, ss / (2.0 * float(n - npar)) - gain * gain * float(n) / sw)
        var = 1.0 / sw + a1 * a1 / (l1 * sw)
        if full:
            var += a2 * a2 / (l2 * sw)
        qs = gain * query_sigma[i]
        out_uv[i] = x
        out_sigma2[i] = wp.max(wp.sqrt(gain * gain * scale * var + MODEL_SHARE * model2), SIGMA_FLOOR_PX)
        out_sigma1[i] = wp.max(wp.sqrt(qs * qs + MODEL_SHARE * model2), SIGMA_FLOOR_PX)
        if maps:
            # (rank one where the neighbours lie on a line: along it only, across it unknown)
            out_map[i] = wp.vec4(A[0, 0], A[0, 1], A[1, 0], A[1, 1])
            out_query_model[i] = wp.sqrt(MODEL_SHARE * model2)
        st = MATCH_OK
        break
    if st != MATCH_OK:
        out_uv[i] = wp.vec2(0.0, 0.0)
        out_sigma2[i] = 0.0
        out_sigma1[i] = 0.0
        if maps:
            out_map[i] = wp.vec4(0.0, 0.0, 0.0, 0.0)
            out_query_model[i] = 0.0
    status[i] = st


# ----------------------------------------------------------------------------- host


def projector_coordinates(rho: wp.array, phi: wp.array, sigma_rho: wp.array, sigma_tan: wp.array, *,
                          center: tuple[float, float]) -> tuple[wp.array, wp.array]:
    """Samples' polar projector coordinates -> projector pixels.

    Args:
        rho, phi, sigma_rho, sigma_tan: (n,) float32 (phi NaN where unknown).
        center: the pattern centre (c_u, c_v), projector px.

    Returns:
        (proj (n,) vec2: c + rho (cos phi, sin phi), NaN where phi is; sigma (n,)
        float32: the isotropic sqrt((sigma_rho^2 + sigma_tan^2) / 2)), on rho's device.
    """
    n = check_array("rho", rho, None, wp.float32, "projector_coordinates")
    for name, a in (("phi", phi), ("sigma_rho", sigma_rho), ("sigma_tan", sigma_tan)):
        check_array(name, a, n, wp.float32, "projector_coordinates")
    dev = rho.device
    proj = wp.empty(n, dtype=wp.vec2, device=dev)
    sigma = wp.empty(n, dtype=wp.float32, device=dev)
    if n:
        wp.launch(polar_coordinates_kernel, dim=n, inputs=[rho, phi, sigma_rho, sigma_tan, wp.vec2(*center)],
                  outputs=[proj, sigma], device=dev)
    return proj, sigma


def _bin_by_projector(proj2: wp.array, uv2: wp.array, sigma2: wp.array, size: tuple[int, int],
                      settings: MatchSettings) -> tuple[tuple, tuple]:
    """Camera 2's samples binned by projector pixel into a grid of cells on their device.

    Returns the grid (cell px, rings of cells the search reads, nx, ny, offsets, counts, items, sat): cell
    c's samples are items[offsets[c]:offsets[c] + counts[c]], sat the counts' summed-area table; and (proj2,
    uv2, sigma2) in the grid's order (place s holds sample items[s]).
    """
    W, Hh = size
    m = proj2.shape[0]
    dev = proj2.device
    cell = float(settings.cell_px)
    rings = int(np.ceil(settings.radius_px / cell))
    nx = int(np.ceil(W / cell))
    ny = int(np.ceil(Hh / cell))
    # A dense map (camera 2 finer than the projector: ~100 samples a 4 px cell) is binned finer: each
    # cell split in 2 x 2 while the cells would still hold a quarter of the neighbours on average, so
    # a query reads ~50 samples, not ~900. The grid covers the same extent and the search the same
    # radius (cell / 2^s, rings 2^s, both exact): the same neighbours, the same matches.
    split = 0
    while split < MAX_GRID_SPLIT and m / (nx * ny * 4.0 ** (split + 1)) >= settings.neighbours / 4.0:
        split += 1
    cell, rings, nx, ny = cell / 2 ** split, rings * 2 ** split, nx * 2 ** split, ny * 2 ** split
    counts = wp.zeros(nx * ny, dtype=wp.int32, device=dev)
    if m:
        wp.launch(count_cells_kernel, dim=m, inputs=[proj2, cell, nx, ny], outputs=[counts], device=dev)
    offsets, total = scan_counts(counts)
    sat = wp.zeros((nx + 1) * (ny + 1), dtype=wp.int32, device=dev)
    wp.launch(sat_rows_kernel, dim=ny, inputs=[counts, nx], outputs=[sat], device=dev)
    wp.launch(sat_cols_kernel, dim=nx + 1, inputs=[ny, nx], outputs=[sat], device=dev)
    items = wp.zeros(max(total, 1), dtype=wp.int32, device=dev)
    sorted_ = (wp.zeros(max(total, 1), dtype=wp.vec2, device=dev), wp.zeros(max(total, 1), dtype=wp.vec2, device=dev),
               wp.zeros(max(total, 1), dtype=wp.float32, device=dev))
    if total:
        cursor = wp.zeros(nx * ny, dtype=wp.int32, device=dev)
        wp.launch(write_cells_kernel, dim=m, inputs=[proj2, cell, nx, ny, offsets], outputs=[cursor, items],
                  device=dev)
        wp.launch(gather_cells_kernel, dim=total, inputs=[items, proj2, uv2, sigma2], outputs=list(sorted_),
                  device=dev)
    return (cell, rings, nx, ny, offsets, counts, items, sat), sorted_


def match_by_projector(
    query: wp.array,
    query_sigma: wp.array,
    proj2: wp.array,
    uv2: wp.array,
    sigma2: wp.array,
    *,
    projector_size: tuple[int, int],
    settings: MatchSettings = MatchSettings(),
    maps: bool = True,
    threads: int | None = None,
) -> Matches:
    """Camera-2 positions of equal projector coordinate (no extrinsics used).

    Args:
        query: (n,) vec2 projector pixels of camera 1's samples (NaN: none).
        query_sigma: (n,) float32 their standard deviations (projector px).
        proj2: (m,) vec2 projector pixels of camera 2's samples.
        uv2: (m,) vec2 camera-2 pixels of those samples.
        sigma2: (m,) float32 standard deviations of proj2 (projector px).
        projector_size: (width, height) of the projector grid; samples outside are not binned.
        settings: :class:`MatchSettings`.
        maps: write ``proj_map`` and ``query_model`` (what a three-ray triangulation reads); False: each is a
            one-element placeholder.
        threads: CPU threads; default all cores.

    Returns:
        :class:`Matches` on the queries' device.
    """
    fn = "match_by_projector"
    n = check_array("query", query, None, wp.vec2, fn)
    check_array("query_sigma", query_sigma, n, wp.float32, fn)
    m = check_array("proj2", proj2, None, wp.vec2, fn)
    check_array("uv2", uv2, m, wp.vec2, fn)
    check_array("sigma2", sigma2, m, wp.float32, fn)
    W, Hh = (int(x) for x in projector_size)
    if W < 1 or Hh < 1:
        raise ValueError(f"{fn}: bad projector_size {projector_size}")
    dev = query.device
    if proj2.device != dev:
        raise ValueError(f"{fn}: camera 2's samples are on {proj2.device}, the queries on {dev}")
    out = Matches(uv2=wp.empty(n, dtype=wp.vec2, device=dev), sigma2=wp.empty(n, dtype=wp.float32, device=dev),
                  sigma1=wp.empty(n, dtype=wp.float32, device=dev), gain=wp.empty(n, dtype=wp.float32, device=dev),
                  proj_map=wp.empty(n if maps else 1, dtype=wp.vec4, device=dev),
                  query_model=wp.empty(n if maps else 1, dtype=wp.float32, device=dev),
                  fit_px=wp.empty(n, dtype=wp.float32, device=dev), status=wp.empty(n, dtype=wp.int32, device=dev))
    if n == 0:
        return out
    (cell, rings, nx, ny, offsets, counts, items, sat), (proj2s, uv2s, sigma2s) = _bin_by_projector(
        proj2, uv2, sigma2, (W, Hh), settings)
    s = settings
    params = MatchParams()
    params.cell = cell
    params.nx = nx
    params.ny = ny
    params.rings = rings
    params.k_max = int(s.neighbours)
    params.k_min = int(s.min_neighbours)
    params.line_ratio = float(LINE_RATIO)
    params.max_offset = float(s.max_offset_px)
    params.max_extrapolation = float(s.max_extrapolation)
    params.max_fit = float(s.max_fit_px)
    params.max_gain = float(s.max_gain)
    params.maps = 1 if maps else 0
    args = [query, query_sigma, proj2s, uv2s, sigma2s, offsets, counts, items, sat, params]
    outputs = [out.uv2, out.sigma2, out.sigma1, out.gain, out.proj_map, out.query_model, out.fit_px, out.status]
    threads = default_threads() if threads is None else threads
    launch_spans(match_kernel, n, lambda i0: args + [i0], outputs, dev, threads)
    return out

