"""The error model's per-sample work on the samples' device (docs/reconstruction.md, "Honest
sigma"): ``pipeline.reconstruct.error_scale`` fits the model on the host from a bounded subset of
the samples (at most ``MAX_CHECK_SAMPLES``, gathered by ``kernels.compact``); what touches every
sample stays here: the fitted terms applied to every sample (``widen_sigmas``: the same values to
the bit as ``error_scale.apply_error_model`` and ``region_scale`` in NumPy), and the error both
coordinates share on a steep surface (``widen_for_slope``)."""

from __future__ import annotations

import numpy as np
import warp as wp

from ringscan.kernels.compact import pixel_rows
from ringscan.kernels.launch import check_array, default_threads, launch_spans

wp.set_module_options({"enable_backward": False})  # no gradients are taken here: no adjoint code to compile

__all__ = ["ErrorTerms", "SLOPE_RADIUS_PX", "widen_for_slope", "widen_sigmas"]

SLOPE_RADIUS_PX = 6
"""Half-side (camera px) of the square whose points give a ring sample's depth gradient across the
image (``widen_for_slope``): wide enough to hold the next rings' samples (a few px apart on the
default rig), narrow enough to stay on one surface."""


@wp.struct
class ErrorTerms:
    """The fitted terms one coordinate's sigma is widened by (``error_scale.ErrorModel``)."""

    k: wp.float64
    """Factor on the decode's sigma."""
    floor2: wp.float64
    """The floor's square (projector px^2), as the host squares it."""
    indirect_px: wp.float64
    """px per unit of indirect share above the view's median (0: no term)."""
    indirect_median: wp.float64
    """The view's median share (``median``)."""
    shading_px: wp.float64
    """px per unit of the light's relative gradient (``Samples.shading``, per camera px; 0: no term)."""
    tile_px: wp.float64
    """Side of the tiles of the factor grid (px)."""
    tx0: int
    """The grid's first tile column."""
    ty0: int
    """The grid's first tile row."""


# ----------------------------------------------------------------------------- kernels


@wp.kernel
def widen_kernel(
    sigma: wp.array(dtype=wp.float32),
    indirect: wp.array(dtype=wp.float32),
    shading: wp.array(dtype=wp.float32),
    uv: wp.array(dtype=wp.vec2),
    grid: wp.array2d(dtype=wp.float64),
    terms: ErrorTerms,
    i0: int,
    out: wp.array(dtype=wp.float32),
):
    """out[i] = float32(sqrt(k^2 s^2 + floor^2 + (indirect_px max(b - median, 0))^2 + (shading_px g)^2)),
    times the square root of the factor of the tile under uv[i] where ``grid`` has tiles (rounded to
    float32 after).

    sigma (n,) float32 the decode's s (projector px); indirect (n,) float32 each sample's share b
    (read only with indirect_px > 0); shading (n,) float32 its light's gradient g (read only with
    shading_px > 0); uv (n,) vec2 (read only with a grid of tiles); grid (rows,
    cols) float64 the tiles' variance factors (1 where none; (0, 0): no tiles): read. out (n,)
    float32: written.

    Size: the four per-sample arrays, the tiles' grid, the terms, the span's i0, one array out."""
    i = i0 + wp.tid()
    ks = terms.k * wp.float64(sigma[i])
    var = ks * ks + terms.floor2
    if terms.indirect_px > wp.float64(0.0):
        b = terms.indirect_px * wp.max(wp.float64(indirect[i]) - terms.indirect_median, wp.float64(0.0))
        var = var + b * b
    if terms.shading_px > wp.float64(0.0):
        g = terms.shading_px * wp.float64(shading[i])
        var = var + g * g
    w = wp.float32(wp.sqrt(var))
    if grid.shape[0] > 0:
        tx = int(wp.floor(wp.float64(uv[i][0]) / terms.tile_px)) - terms.tx0
        ty = int(wp.floor(wp.float64(uv[i][1]) / terms.tile_px)) - terms.ty0
        f = wp.float64(1.0)
        if tx >= 0 and tx < grid.shape[1] and ty >= 0 and ty < grid.shape[0]:
            f = grid[ty, tx]
        w = wp.float32(wp.float64(w) * wp.sqrt(f))
    out[i] = w


@wp.kernel
def first_sample_kernel(pixel: wp.array(dtype=wp.int32), status: wp.array(dtype=wp.int32),
                        points: wp.array(dtype=wp.vec3), center: wp.vec3d, i0: int,
                        at_pixel: wp.array(dtype=wp.int32), depth: wp.array(dtype=wp.float64)):
    """at_pixel[pixel[i]] = the least i of the placed points (status 0) at each pixel (atomic: the same
    on every device); depth[i] = the point's distance from the camera centre (mm). pixel, status (n,)
    int32, points (n,) vec3: read; at_pixel (npix,) int32 (set to n before), depth (n,) float64: written."""
    i = i0 + wp.tid()
    depth[i] = wp.length(wp.vec3d(points[i]) - center)
    if status[i] == 0:
        wp.atomic_min(at_pixel, pixel[i], i)


@wp.kernel
def row_sums_kernel(rank: wp.array(dtype=wp.int32), listed: wp.array(dtype=wp.int32), uv: wp.array(dtype=wp.vec2),
                    depth: wp.array(dtype=wp.float64), width: int, y0: int, first: wp.array(dtype=wp.spatial_vectord),
                    second: wp.array(dtype=wp.vec3d)):
    """Each image row's running sums of its listed points' moments, in ``compact.pixel_rows``' order (one
    thread a row, from y0): first[k] = the sums of (1, u, v, u^2, u v, v^2) and second[k] = of (d, u d, v d)
    over the row's points up to and including the k-th listed one. A window's row then sums its points
    by one difference, whatever their number. rank (H W + 1,), listed (n,) int32, uv (n,) vec2, depth (n,)
    float64: read; first (n,) spatial_vectord, second (n,) vec3d: written (the listed entries)."""
    y = y0 + wp.tid()
    a = wp.spatial_vectord()
    b = wp.vec3d()
    for k in range(rank[y * width], rank[(y + 1) * width]):
        j = listed[k]
        u = wp.float64(uv[j][0])
        v = wp.float64(uv[j][1])
        d = depth[j]
        a = a + wp.spatial_vectord(wp.float64(1.0), u, v, u * u, u * v, v * v)
        b = b + wp.vec3d(d, u * d, v * d)
        first[k] = a
        second[k] = b


@wp.kernel
def slope_kernel(
    rank: wp.array(dtype=wp.int32),
    first: wp.array(dtype=wp.spatial_vectord),
    second: wp.array(dtype=wp.vec3d),
    uv: wp.array(dtype=wp.vec2),
    depth: wp.array(dtype=wp.float64),
    status: wp.array(dtype=wp.int32),
    sigma: wp.array(dtype=wp.float32),
    width: int,
    radius: int,
    position_px: wp.float64,
    i0: int,
    gradient: wp.array(dtype=wp.float32),
    out: wp.array(dtype=wp.float32),
):
    """Each placed point's depth gradient across the image (mm per camera px: a plane fitted to the
    depths of the placed points within ``radius`` px, 0 where fewer than 6 or all along one line) and
    its sigma widened by it: out = sqrt(sigma^2 + (position_px * gradient)^2); out = sigma elsewhere.

    rank (npix + 1,) int32 the occupied pixels before each pixel (row-major, ``compact.pixel_rows``: a row's
    points from x0 to x1 are its entries rank[y W + x0] .. rank[y W + x1 + 1] - 1), first, second (n,) the
    rows' running moment sums (:func:`row_sums_kernel`); uv (n,) vec2; depth (n,) float64 along the rays;
    status (n,) int32; sigma (n,) float32: read. gradient, out (n,) float32: written.

    Size: the pixel index and the rows' sums (three arrays), the four per-sample arrays the fit reads, the
    camera's width, the square's half-side, the position error, the span's i0, two arrays out."""
    i = i0 + wp.tid()
    out[i] = sigma[i]
    gradient[i] = wp.float32(0.0)
    if status[i] != 0:
        return
    height = (rank.shape[0] - 1) / width
    di = depth[i]
    ui = wp.float64(uv[i][0])
    vi = wp.float64(uv[i][1])
    x = int(wp.round(uv[i][0]))
    y = int(wp.round(uv[i][1]))
    a = wp.spatial_vectord()
    b = wp.vec3d()
    x0 = wp.max(x - radius, 0)
    x1 = wp.min(x + radius, width - 1)
    for yy in range(wp.max(y - radius, 0), wp.min(y + radius, height - 1) + 1):
        # the row's points within the square: its running sums at the last one less those before the first
        k0 = rank[yy * width + x0]
        k1 = rank[yy * width + x1 + 1]
        if k1 > k0:
            a = a + first[k1 - 1]
            b = b + second[k1 - 1]
            if k0 > rank[yy * width]:
                a = a - first[k0 - 1]
                b = b - second[k0 - 1]
    s1 = a[0]
    if s1 < wp.float64(6.0):
        return
    # the moments about the point, then the plane's slope from the centred sums; both directions spread (a
    # lone ring is a line)
    su = a[1] - s1 * ui
    sv = a[2] - s1 * vi
    suu = a[3] - wp.float64(2.0) * ui * a[1] + s1 * ui * ui
    suv = a[4] - ui * a[2] - vi * a[1] + s1 * ui * vi
    svv = a[5] - wp.float64(2.0) * vi * a[2] + s1 * vi * vi
    sd = b[0] - s1 * di
    sud = b[1] - ui * b[0] - di * a[1] + s1 * ui * di
    svd = b[2] - vi * b[0] - di * a[2] + s1 * vi * di
    cuu = suu - su * su / s1
    cuv = suv - su * sv / s1
    cvv = svv - sv * sv / s1
    bu = sud - su * sd / s1
    bv = svd - sv * sd / s1
    det = cuu * cvv - cuv * cuv
    half = wp.float64(0.5) * (cuu + cvv)
    if det <= wp.float64(0.05) * half * half:
        return
    gu = (cvv * bu - cuv * bv) / det
    gv = (cuu * bv - cuv * bu) / det
    g = wp.sqrt(gu * gu + gv * gv)
    gradient[i] = wp.float32(g)
    e = position_px * g
    out[i] = wp.float32(wp.sqrt(wp.float64(sigma[i]) * wp.float64(sigma[i]) + e * e))


# ----------------------------------------------------------------------------- host


def widen_for_slope(points: wp.array, status: wp.array, sigma: wp.array, uv: wp.array, pixel: wp.array, *,
                    center, width: int, height: int, position_px: float, radius: int = SLOPE_RADIUS_PX,
                    threads: int | None = None) -> tuple[wp.array, wp.array]:
    """((n,) float32 sigmas widened by the error both projector coordinates share on a steep surface,
    (n,) float32 each point's depth gradient across the image, mm per camera px; :func:`slope_kernel`),
    on the points' device. A camera-side error of the sample's place moves the ray, and along a
    surface that the view grazes the depth changes fast across the image: both coordinates' points
    then err alike by ``position_px`` times that gradient, which their disagreement cannot show.

    Size: the triangulation's three per-point arrays, the samples' positions and pixels, the camera
    (centre, size), the position error, the square's half-side, the thread count."""
    fn = "widen_for_slope"
    n = check_array("points", points, None, wp.vec3, fn)
    check_array("status", status, n, wp.int32, fn)
    check_array("sigma", sigma, n, wp.float32, fn)
    check_array("uv", uv, n, wp.vec2, fn)
    check_array("pixel", pixel, n, wp.int32, fn)
    dev = points.device
    th = default_threads() if threads is None else threads
    at_pixel = wp.full(int(width) * int(height), n, dtype=wp.int32, device=dev)
    gradient = wp.empty(n, dtype=wp.float32, device=dev)
    out = wp.empty(n, dtype=wp.float32, device=dev)
    if n == 0:
        return out, gradient
    depth = wp.empty(n, dtype=wp.float64, device=dev)
    c = np.asarray(center, np.float64).reshape(3)
    launch_spans(first_sample_kernel, n, lambda i0: [pixel, status, points, wp.vec3d(*c), i0], [at_pixel, depth],
                 dev, 1)
    rank, listed = pixel_rows(at_pixel, n)  # the occupied pixels row by row: each row's points read in x order
    first = wp.empty(n, dtype=wp.spatial_vectord, device=dev)
    second = wp.empty(n, dtype=wp.vec3d, device=dev)
    launch_spans(row_sums_kernel, int(height), lambda y0: [rank, listed, uv, depth, int(width), y0], [first, second],
                 dev, th, min_span=64)
    args = [rank, first, second, uv, depth, status, sigma, int(width), int(radius), float(position_px)]
    launch_spans(slope_kernel, n, lambda i0: args + [i0], [gradient, out], dev, th)
    return out, gradient



def widen_sigmas(sigma: wp.array, *, k: float, floor: float, indirect: wp.array | None = None,
                 indirect_px: float = 0.0, indirect_median: float = 0.0, shading: wp.array | None = None,
                 shading_px: float = 0.0, uv: wp.array | None = None, regions: dict | None = None,
                 threads: int | None = None) -> wp.array:
    """(n,) float32 sigmas widened by one coordinate's fitted terms (:func:`widen_kernel`), on sigma's
    device: ``error_scale.apply_error_model`` (k, floor, the indirect share above ``indirect_median``
    at ``indirect_px`` a unit, the light's gradient ``shading`` at ``shading_px`` a unit) times the
    square root of ``regions``' tile factor (``error_scale.region_scale``: {"tile_px", "scales":
    [[tx, ty, factor], ...]}) under ``uv``.

    Size: the sigmas, the model's five terms for this coordinate (k, floor, indirect px and median,
    shading px), the three per-sample arrays they read (indirect, shading, uv), the tiles, the thread
    count."""
    fn = "widen_sigmas"
    n = check_array("sigma", sigma, None, wp.float32, fn)
    dev = sigma.device
    use_indirect = indirect_px > 0 and indirect is not None
    if use_indirect:
        check_array("indirect", indirect, n, wp.float32, fn)
    use_shading = shading_px > 0 and shading is not None
    if use_shading:
        check_array("shading", shading, n, wp.float32, fn)
    table = np.asarray(regions["scales"], np.float64).reshape(-1, 3) if regions and regions.get("scales") else None
    terms = ErrorTerms()
    terms.k = float(k)
    terms.floor2 = float(floor) ** 2
    terms.indirect_px = float(indirect_px) if use_indirect else 0.0
    terms.indirect_median = float(indirect_median)
    terms.shading_px = float(shading_px) if use_shading else 0.0
    terms.tile_px = float(regions["tile_px"]) if table is not None else 1.0
    if table is not None:
        check_array("uv", uv, n, wp.vec2, fn)
        tx, ty = table[:, 0].astype(np.int64), table[:, 1].astype(np.int64)
        terms.tx0, terms.ty0 = int(tx.min()), int(ty.min())
        cells = np.ones((int(ty.max()) - terms.ty0 + 1, int(tx.max()) - terms.tx0 + 1))
        cells[ty - terms.ty0, tx - terms.tx0] = table[:, 2]
        grid = wp.array(cells, dtype=wp.float64, device=dev)
    else:
        terms.tx0 = terms.ty0 = 0
        grid = wp.empty((0, 0), dtype=wp.float64, device=dev)
    out = wp.empty(n, dtype=wp.float32, device=dev)
    no_uv = wp.empty(0, dtype=wp.vec2, device=dev)
    args = [sigma, indirect if use_indirect else sigma, shading if use_shading else sigma,
            uv if table is not None else no_uv, grid, terms]
    launch_spans(widen_kernel, n, lambda i0: args + [i0], [out], dev, default_threads() if threads is None else threads)
    return out
