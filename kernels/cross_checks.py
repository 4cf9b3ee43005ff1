"""The neighbour model's checks across rings (docs/reconstruction.md, "Honest sigma", "Without an
angle"): a ring sample that no check along its ring reaches is checked against the samples of other
rings around it, a quadratic of depth over the image fitted to them (weighted, refitted without the
far ones) and read at its own position; ``pipeline.reconstruct.neighbour_checks._cross_ring_checks`` is
the NumPy statement. One thread a checked sample, in float64."""

from __future__ import annotations

import numpy as np
import warp as wp

from ringscan.kernels.compact import pixel_rows
from ringscan.kernels.launch import check_array, default_threads, launch_spans

__all__ = ["CrossCheck", "cross_check_kernel", "cross_ring_checks"]

# no gradients here, and loops left as loops (the 6x6 fits' loops unrolled would make compiling slow)
wp.set_module_options({"enable_backward": False, "max_unroll": 1})

MAT66D = wp.types.matrix(shape=(6, 6), dtype=wp.float64)
VEC6D = wp.types.vector(length=6, dtype=wp.float64)
FAR = wp.constant(wp.float64(1e300))
"""A residual's stand-in where there is no neighbour (the NumPy statement's inf)."""
MIN_CROSS_NEIGHBOURS = wp.constant(18)
"""At least three neighbours a term of the quadratic (``neighbour_checks._cross_fit``)."""


@wp.struct
class CrossCheck:
    """The settings of one run of the checks across rings (``neighbour_checks._cross_ring_checks``)."""

    width: int
    """Camera width (px)."""
    height: int
    """Rows the pixel index covers."""
    reject: wp.float64
    """A neighbour farther off the first fit than this many of its robust spreads is left out of the second."""
    gate: wp.float64
    """A fit whose neighbours spread more than this (robustly, in their sigmas) makes no check."""
    max_cond: wp.float64
    """The normal matrix's largest condition number."""


# ----------------------------------------------------------------------------- functions


@wp.func
def design_row(du: wp.float64, dv: wp.float64):
    """The quadratic's terms at (du, dv): 1, du, dv, du^2, du dv, dv^2."""
    return VEC6D(wp.float64(1.0), du, dv, du * du, du * dv, dv * dv)


@wp.func
def moment_matrix(m00: wp.float64, m10: wp.float64, m01: wp.float64, m20: wp.float64, m11: wp.float64,
                  m02: wp.float64, m30: wp.float64, m21: wp.float64, m12: wp.float64, m03: wp.float64,
                  m40: wp.float64, m31: wp.float64, m22: wp.float64, m13: wp.float64, m04: wp.float64):
    """The normal matrix sum w a a^T of the quadratic's terms a = (1, u, v, u^2, u v, v^2) from the weighted
    moments m_ik = sum w u^i v^k.

    Size: the 15 moments of order up to 4."""
    return MAT66D(m00, m10, m01, m20, m11, m02,
                  m10, m20, m11, m30, m21, m12,
                  m01, m11, m02, m21, m12, m03,
                  m20, m30, m21, m40, m31, m22,
                  m11, m21, m12, m31, m22, m13,
                  m02, m12, m03, m22, m13, m04)


@wp.func
def symmetric_condition(N: MAT66D):
    """The 2-norm condition number of the symmetric N to ~0.2 % (its eigenvalues by cyclic Jacobi
    rotations until each is known to 1e-3 of the smallest); FAR where the smallest is 0."""
    A = N
    for sweep in range(30):
        off = wp.float64(0.0)
        low = wp.abs(A[0, 0])
        for p in range(6):
            low = wp.min(low, wp.abs(A[p, p]))
            for q in range(p + 1, 6):
                off += A[p, q] * A[p, q]
        # every eigenvalue lies within the off-diagonal's norm of a diagonal entry (Weyl): below 1e-3 of
        # the smallest, the condition number is the diagonal's to 0.2 % (a test against 1e12 only)
        if off <= wp.float64(1e-6) * low * low:
            break
        for p in range(6):
            for q in range(p + 1, 6):
                apq = A[p, q]
                if apq != wp.float64(0.0):
                    theta = (A[q, q] - A[p, p]) / (wp.float64(2.0) * apq)
                    t = wp.float64(1.0) / (wp.abs(theta) + wp.sqrt(theta * theta + wp.float64(1.0)))
                    if theta < wp.float64(0.0):
                        t = -t
                    c = wp.float64(1.0) / wp.sqrt(t * t + wp.float64(1.0))
                    s = t * c
                    for k in range(6):
                        akp = A[k, p]
                        akq = A[k, q]
                        A[k, p] = c * akp - s * akq
                        A[k, q] = s * akp + c * akq
                    for k in range(6):
                        apk = A[p, k]
                        aqk = A[q, k]
                        A[p, k] = c * apk - s * aqk
                        A[q, k] = s * apk + c * aqk
    lo = wp.abs(A[0, 0])
    hi = wp.abs(A[0, 0])
    for i in range(1, 6):
        lo = wp.min(lo, wp.abs(A[i, i]))
        hi = wp.max(hi, wp.abs(A[i, i]))
    cond = FAR
    if lo > wp.float64(0.0):
        cond = hi / lo
    return cond


@wp.func
def condition_below(N: MAT66D, limit: wp.float64):
    """Whether the symmetric positive semi-definite N's 2-norm condition number is below ``limit``:
    decided by cheap bounds where they settle it, else by :func:`symmetric_condition` (a third of the
    checks' time when run on every fit). With N = L L^T (Cholesky), lambda_max lies in
    [max diag N, trace N] and 1 / lambda_min in [max diag N^-1, trace N^-1]; their products bound the
    condition number within a factor of 36, and a typical fit's lies far below the limit."""
    L = MAT66D()
    ok = bool(True)
    for j in range(6):
        d = N[j, j]
        for k in range(j):
            d = d - L[j, k] * L[j, k]
        if d <= wp.float64(0.0):
            ok = False
        if ok:
            L[j, j] = wp.sqrt(d)
            for i in range(j + 1, 6):
                acc = N[i, j]
                for k in range(j):
                    acc = acc - L[i, k] * L[j, k]
                L[i, j] = acc / L[j, j]
    decided = bool(False)
    below = bool(False)
    if ok:
        # L^-1 (lower triangular) by forward substitution; diag(N^-1)_i = sum_k (L^-1)[k, i]^2
        Li = MAT66D()
        for j in range(6):
            Li[j, j] = wp.float64(1.0) / L[j, j]
            for i in range(j + 1, 6):
                acc = wp.float64(0.0)
                for k in range(j, i):
                    acc = acc + L[i, k] * Li[k, j]
                Li[i, j] = -acc / L[i, i]
        tr = wp.float64(0.0)
        dmax = wp.float64(0.0)
        tri = wp.float64(0.0)
        imax = wp.float64(0.0)
        for i in range(6):
            tr = tr + N[i, i]
            dmax = wp.max(dmax, N[i, i])
            di = wp.float64(0.0)
            for k in range(i, 6):
                di = di + Li[k, i] * Li[k, i]
            tri = tri + di
            imax = wp.max(imax, di)
        # a margin of 1 % over the rounding of a condition number up to the limit (1e12 * 1e-16 relative)
        if tr * tri < wp.float64(0.99) * limit:
            decided = True
            below = True
        elif dmax * imax > wp.float64(1.01) * limit:
            decided = True
    if not decided:
        below = symmetric_condition(N) < limit
    return below


@wp.func
def solve6(N: MAT66D, b: VEC6D):
    """x with N x = b (Gaussian elimination with partial pivoting)."""
    A = N
    x = b
    for col in range(6):
        piv = col
        for r in range(col + 1, 6):
            if wp.abs(A[r, col]) > wp.abs(A[piv, col]):
                piv = r
        if piv != col:
            for k in range(6):
                tmp = A[col, k]
                A[col, k] = A[piv, k]
                A[piv, k] = tmp
            tb = x[col]
            x[col] = x[piv]
            x[piv] = tb
        for r in range(col + 1, 6):
            f = A[r, col] / A[col, col]
            for k in range(col, 6):
                A[r, k] = A[r, k] - f * A[col, k]
            x[r] = x[r] - f * x[col]
    for ii in range(6):
        i = 5 - ii
        acc = x[i]
        for k in range(i + 1, 6):
            acc = acc - A[i, k] * x[k]
        x[i] = acc / A[i, i]
    return x


@wp.func
def select_kth(z: wp.array2d(dtype=wp.float64), row: int, n: int, k: int):
    """The k-th smallest of z[row, :n] (Hoare's quickselect; reorders them)."""
    lo = int(0)
    hi = n - 1
    while lo < hi:
        pivot = z[row, (lo + hi) / 2]
        i = lo
        j = hi
        while i <= j:
            while z[row, i] < pivot:
                i += 1
            while z[row, j] > pivot:
                j -= 1
            if i <= j:
                tmp = z[row, i]
                z[row, i] = z[row, j]
                z[row, j] = tmp
                i += 1
                j -= 1
        if k <= j:
            hi = j
        elif k >= i:
            lo = i
        else:
            lo = k
            hi = k
    return z[row, k]


@wp.func
def cross_usable(ring: wp.array(dtype=wp.int32), depth: wp.array(dtype=wp.float64), var: wp.array(dtype=wp.float64),
                 j: int, kc: int):
    """Whether a check across rings uses sample j: another ring's than ``kc``, with a finite depth and a
    variance > 0."""
    return ring[j] != kc and wp.isfinite(depth[j]) and var[j] > wp.float64(0.0)


@wp.func
def cross_fit(uv: wp.array(dtype=wp.vec2d), depth: wp.array(dtype=wp.float64), var: wp.array(dtype=wp.float64),
              c: int, count: int, limit: wp.float64, store: bool, cc: CrossCheck, row: int,
              nbr: wp.array2d(dtype=wp.int32), res: wp.array2d(dtype=wp.float64), work: wp.array2d(dtype=wp.float64)):
    """One weighted fit of sample c's check (``neighbour_checks._cross_fit``) to its ``count`` neighbours
    nbr[row, :count] whose res[row] is at most ``limit``: (the normal matrix, whether the fit can be made,
    the robust spread of their normalised residuals); with ``store`` their residuals go to res[row] (FAR:
    left out); work[row] holds them for the median.

    Size: the three per-sample arrays a fit reads, the centre and its neighbours' count, the mask's
    limit and whether to keep the residuals, the settings, the centre's row and its three scratch rows."""
    # N's 36 entries are 15 weighted moments sum w u^i v^k (i + k <= 4) of the quadratic's terms: summed
    # once each (a third of the outer products' work), N then filled from them (exactly symmetric)
    rhs = VEC6D()
    m00 = wp.float64(0.0)
    m10 = wp.float64(0.0)
    m01 = wp.float64(0.0)
    m20 = wp.float64(0.0)
    m11 = wp.float64(0.0)
    m02 = wp.float64(0.0)
    m30 = wp.float64(0.0)
    m21 = wp.float64(0.0)
    m12 = wp.float64(0.0)
    m03 = wp.float64(0.0)
    m40 = wp.float64(0.0)
    m31 = wp.float64(0.0)
    m22 = wp.float64(0.0)
    m13 = wp.float64(0.0)
    m04 = wp.float64(0.0)
    cnt = int(0)
    for t in range(count):
        if res[row, t] <= limit:
            j = nbr[row, t]
            du = uv[j][0] - uv[c][0]
            dv = uv[j][1] - uv[c][1]
            w = wp.float64(1.0) / var[j]
            rhs = rhs + (w * depth[j]) * design_row(du, dv)
            wu = w * du
            wv = w * dv
            wuu = wu * du
            wuv = wu * dv
            wvv = wv * dv
            m00 += w
            m10 += wu
            m01 += wv
            m20 += wuu
            m11 += wuv
            m02 += wvv
            m30 += wuu * du
            m21 += wuu * dv
            m12 += wuv * dv
            m03 += wvv * dv
            m40 += wuu * du * du
            m31 += wuu * du * dv
            m22 += wuu * dv * dv
            m13 += wuv * dv * dv
            m04 += wvv * dv * dv
            cnt += 1
    N = moment_matrix(m00, m10, m01, m20, m11, m02, m30, m21, m12, m03, m40, m31, m22, m13, m04)
    good = cnt >= MIN_CROSS_NEIGHBOURS
    if good:
        good = condition_below(N, cc.max_cond)
    spread = wp.float64(0.0)
    if good:
        beta = solve6(N, rhs)
        n = int(0)
        for t in range(count):
            zo = FAR
            if res[row, t] <= limit:
                j = nbr[row, t]
                a = design_row(uv[j][0] - uv[c][0], uv[j][1] - uv[c][1])
                zo = wp.abs(depth[j] - wp.dot(a, beta)) * wp.sqrt(wp.float64(1.0) / var[j])
                work[row, n] = zo
                n += 1
            if store:
                res[row, t] = zo
        # the median as the NumPy statement reads it off each sorted row: (m // 2 + (m + 1) // 2) / 2, m = n - 1
        mid = wp.max(n - 1, 0)
        k1 = mid / 2
        v1 = select_kth(work, row, n, k1)
        v2 = v1
        if (mid + 1) / 2 > k1:
            v2 = work[row, k1 + 1]
            for t in range(k1 + 2, n):
                v2 = wp.min(v2, work[row, t])
        spread = wp.float64(0.5) * (v1 + v2) / wp.float64(0.6745)
    return N, good, spread


# ----------------------------------------------------------------------------- kernels


@wp.kernel
def cross_check_kernel(
    rank: wp.array(dtype=wp.int32),
    listed: wp.array(dtype=wp.int32),
    ring: wp.array(dtype=wp.int32),
    pixel: wp.array(dtype=wp.int32),
    uv: wp.array(dtype=wp.vec2d),
    depth: wp.array(dtype=wp.float64),
    var: wp.array(dtype=wp.float64),
    half_width: wp.array(dtype=wp.int32),
    centre: wp.array(dtype=wp.int32),
    cc: CrossCheck,
    i0: int,
    nbr: wp.array2d(dtype=wp.int32),
    res: wp.array2d(dtype=wp.float64),
    work: wp.array2d(dtype=wp.float64),
    made: wp.array(dtype=wp.int32),
    r: wp.array(dtype=wp.float64),
    v: wp.array(dtype=wp.float64),
):
    """Each centre sample's depth against the quadratic of depth over the image that the samples of
    other rings within the disc ``half_width`` spans fit, weighted by 1 / var, refitted without the neighbours beyond
    ``cc.reject`` robust spreads (``neighbour_checks._cross_ring_checks``, the NumPy statement):
    made[i] = 1 where the check is made (neighbours of an inner and an outer ring, three rings in
    all, at least three a term, a condition number under ``cc.max_cond``, a spread within
    ``cc.gate``), r[i] its residual and v[i] its predicted variance.

    rank (npix + 1,), listed (n,) int32 the samples at the pixels row by row (``compact.pixel_rows`` of the
    sample at each pixel); ring, pixel (n,) int32; uv (n,) vec2d;
    depth, var (n,) float64; half_width (2 R + 1,) int32 the disc's half-width in each row dy = -R..R
    (its pixel itself left out); centre (m,) int32: read. nbr (m, K) int32, res, work
    (m, K) float64: scratch (a centre's neighbours, found once, and their residuals). made (m,) int32,
    r, v (m,) float64: written.

    Size: the view's index and per-sample arrays, the disc, the centres and settings, the span's
    i0, three scratch rows a centre and the three results."""
    i = i0 + wp.tid()
    c = centre[i]
    kc = ring[c]
    x = pixel[c] % cc.width
    y = pixel[c] / cc.width
    made[i] = 0
    r[i] = wp.float64(0.0)
    v[i] = wp.float64(0.0)
    inner = bool(False)
    outer = bool(False)
    first = int(-1)
    second = int(-1)
    rings = int(0)
    count = int(0)
    rad = (half_width.shape[0] - 1) / 2
    # the neighbours, once, row by row over the disc (dy, then dx: the NumPy statement's order, so its
    # sums): the fits read them from nbr[i]
    for row in range(half_width.shape[0]):
        yy = y + row - rad
        if yy < 0 or yy >= cc.height:
            continue
        w = half_width[row]
        base = yy * cc.width
        # the row's samples within the disc, in x order (its empty pixels not visited)
        for t in range(rank[base + wp.max(x - w, 0)], rank[base + wp.min(x + w, cc.width - 1) + 1]):
            j = listed[t]
            if pixel[j] == pixel[c]:  # the centre's own pixel
                continue
            if not cross_usable(ring, depth, var, j, kc):
                continue
            nbr[i, count] = j
            res[i, count] = wp.float64(0.0)  # the first fit takes every neighbour
            count += 1
            k = ring[j]
            if k < kc:
                inner = True
            if k > kc:
                outer = True
            if rings == 0:
                first = k
                rings = 1
            elif rings == 1 and k != first:
                second = k
                rings = 2
            elif rings == 2 and k != first and k != second:
                rings = 3
    if not (inner and outer and rings >= 3):
        return
    N, good, spread = cross_fit(uv, depth, var, c, count, FAR, True, cc, i, nbr, res, work)
    if not good:
        return
    limit = FAR
    thr = cc.reject * wp.max(spread, wp.float64(1.0))
    far = bool(False)
    for t in range(count):
        if res[i, t] > thr:
            far = True
    if far:
        limit = thr
        N2, good2, spread2 = cross_fit(uv, depth, var, c, count, limit, False, cc, i, nbr, res, work)
        if not good2:
            return
        N = N2
        spread = spread2
    if spread > cc.gate:
        return
    b = solve6(N, VEC6D(wp.float64(1.0), wp.float64(0.0), wp.float64(0.0), wp.float64(0.0), wp.float64(0.0),
                        wp.float64(0.0)))
    fitted = wp.float64(0.0)
    vv = wp.float64(0.0)
    for t in range(count):
        if res[i, t] <= limit:
            j = nbr[i, t]
            wi = wp.dot(design_row(uv[j][0] - uv[c][0], uv[j][1] - uv[c][1]), b) / var[j]
            fitted += wi * depth[j]
            vv += wi * wi * var[j]
    made[i] = 1
    r[i] = depth[c] - fitted
    v[i] = var[c] + vv


# ----------------------------------------------------------------------------- host


def cross_ring_checks(depth: wp.array, var: wp.array, uv: wp.array, ring: wp.array, pixel: wp.array,
                      at_pixel: wp.array, centre: np.ndarray, *, radius: int, width: int, reject: float,
                      gate: float, rows: tuple | None = None,
                      threads: int | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(checked samples (k,) int64, r (k,), predicted variance (k,)) of :func:`cross_check_kernel`
    for the ``centre`` samples, in their order: the checks of the NumPy statement
    (``neighbour_checks._cross_ring_checks``), the same samples where no threshold's test falls
    within rounding and their numbers to ~1e-7 of r and ~1e-12 of the variance (its solves are
    LAPACK's, these the kernel's).

    Args:
        depth, var: (n,) float64 each sample's depth (NaN: not placed) and its predicted variance.
        uv: (n,) vec2d camera positions (px). ring, pixel: (n,) int32 rings and pixels (y * width + x).
        at_pixel: (npix,) int32 the sample at each pixel (-1: none; a sample j only at pixel[j]); npix //
            width rows are looked in.
        centre: (m,) the samples to check. radius: the neighbourhood (px). width: camera width.
        reject, gate: ``neighbour_checks.CROSS_REJECT`` and ``CROSS_GATE``.
        rows: ``compact.pixel_rows(at_pixel, n)``, where the caller checks one view several times (made
            here otherwise).
        threads: CPU threads; default all cores.

    Size: the view's six arrays and their row index (made once for every call of a view), the centres, the
    neighbourhood's radius, the camera's width, the two thresholds and the thread count.
    """
    fn = "cross_ring_checks"
    n = check_array("depth", depth, None, wp.float64, fn)
    check_array("var", var, n, wp.float64, fn)
    check_array("uv", uv, n, wp.vec2d, fn)
    check_array("ring", ring, n, wp.int32, fn)
    check_array("pixel", pixel, n, wp.int32, fn)
    check_array("at_pixel", at_pixel, None, wp.int32, fn)
    centre = np.asarray(centre, np.int64)
    m = centre.size
    if m == 0:
        return np.zeros(0, np.int64), np.zeros(0), np.zeros(0)
    if centre.min() < 0 or centre.max() >= n:
        raise ValueError(f"{fn}: centre indices must lie in [0, {n})")
    dev = depth.device
    rad = int(radius)
    half = np.array([int(np.floor(np.sqrt(rad * rad - dy * dy))) for dy in range(-rad, rad + 1)], np.int32)
    cc = CrossCheck()
    cc.width = int(width)
    cc.height = int(at_pixel.shape[0] // width)
    cc.reject = float(reject)
    cc.gate = float(gate)
    cc.max_cond = 1e12
    k = int(2 * half.sum() + half.size) - 1  # the disc's pixels less its centre
    nbr = wp.empty((m, k), dtype=wp.int32, device=dev)
    res = wp.empty((m, k), dtype=wp.float64, device=dev)
    work = wp.empty((m, k), dtype=wp.float64, device=dev)
    made = wp.empty(m, dtype=wp.int32, device=dev)
    r = wp.empty(m, dtype=wp.float64, device=dev)
    v = wp.empty(m, dtype=wp.float64, device=dev)
    rank, listed = pixel_rows(at_pixel, n) if rows is None else rows
    args = [rank, listed, ring, pixel, uv, depth, var, wp.array(half, dtype=wp.int32, device=dev),
            wp.array(centre.astype(np.int32), dtype=wp.int32, device=dev), cc]
    launch_spans(cross_check_kernel, m, lambda i0: args + [i0], [nbr, res, work, made, r, v], dev,
                 default_threads() if threads is None else threads, min_span=64)
    ok = made.numpy().astype(bool)
    return centre[ok], r.numpy()[ok], v.numpy()[ok]
