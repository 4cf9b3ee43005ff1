"""How far along its ring each sample can be checked (docs/reconstruction.md, "Honest sigma",
"Without an angle"): the neighbour model (``pipeline.reconstruct.neighbour_checks``) checks a sample
against same-ring samples 1, 2, 4 and 8 px to either side; a sample no check reaches (a ring's
fragment, an object's edge) errs more than those it fits, so every sample's reach is wanted,
not only the fit's few thousand. One thread a sample: the same tests as the NumPy statement
(``neighbour_checks._next_neighbours``, ``_ring_directions``, ``_lag_nodes``), in float64."""

from __future__ import annotations

import numpy as np
import warp as wp

from ringscan.kernels.launch import check_array, default_threads, launch_spans

__all__ = ["check_reach_kernel", "next_neighbours_kernel", "ring_sums_kernel", "lag_nodes_kernel",
           "cross_check_kernel", "sample_reach", "next_neighbours", "ring_lag_nodes", "cross_ring_checks"]

# no gradients here, and loops left as loops: unrolled (Warp's default for short constant
# ranges), the 3 lags x 4 nodes x 5 x 5 pixels took minutes to compile on the CPU
wp.set_module_options({"enable_backward": False, "max_unroll": 1})

LAGS = wp.constant(wp.vec3i(2, 4, 8))
"""The checks wider than 1 px (``neighbour_checks.NEIGHBOUR_LAGS[1:]``)."""

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
def keyed_sample(key: wp.array(dtype=wp.int64), order: wp.array(dtype=wp.int32), want: wp.int64):
    """The sample whose ring * npix + pixel is ``want`` (binary search of the sorted ``key``), -1: none."""
    lo = int(0)
    hi = key.shape[0]
    while lo < hi:
        mid = (lo + hi) / 2
        if key[mid] < want:
            lo = mid + 1
        else:
            hi = mid
    found = int(-1)
    if lo < key.shape[0]:
        if key[lo] == want:
            found = order[lo]
    return found


@wp.func
def same_ring_at(at_pixel: wp.array(dtype=wp.int32), ring: wp.array(dtype=wp.int32), width: int, height: int,
                 k: int, x: int, y: int):
    """The sample at pixel (x, y) where it is of ring ``k`` (-1: none, another ring's, or outside)."""
    found = int(-1)
    if x >= 0 and x < width and y >= 0 and y < height:
        j = at_pixel[y * width + x]
        if j >= 0:
            if ring[j] == k:
                found = j
    return found


@wp.func
def uv64(uv: wp.array(dtype=wp.vec2), i: int):
    return wp.vec2d(wp.float64(uv[i][0]), wp.float64(uv[i][1]))


@wp.func
def keyed_neighbour(key: wp.array(dtype=wp.int64), order: wp.array(dtype=wp.int32), k: int, npix: wp.int64,
                    width: int, x: int, y: int, a: int):
    """The sample of ring ``k`` at the a-th of the 8 pixels around (x, y) (row by row, the centre left out;
    -1: none there)."""
    ia = a + wp.where(a >= 4, 1, 0)
    ax = x + ia % 3 - 1
    ay = y + ia / 3 - 1
    j = int(-1)
    if ax >= 0 and ax < width and ay >= 0:
        j = keyed_sample(key, order, wp.int64(k) * npix + wp.int64(ay * width + ax))
    return j


@wp.func
def opposite_pair(uv: wp.array(dtype=wp.vec2), key: wp.array(dtype=wp.int64), order: wp.array(dtype=wp.int32),
                  k: int, npix: wp.int64, width: int, x: int, y: int, c: int):
    """The two samples of ring ``k`` among the 8 pixels around (x, y) most nearly on opposite sides of sample
    ``c`` (the pair of least cosine between their unit offsets, the first such in the 8 x 8 order, both with
    an offset), where at least 120 degrees apart; (-1, -1): none (``_next_neighbours``' test and choice).

    Size: a @wp.func reading the samples and the ring index directly, plus the ring, the index's stride,
    the pixel and the sample."""
    pc = uv64(uv, c)
    best = wp.float64(1.0e308)
    found = int(0)
    ba = int(-1)
    bb = int(-1)
    for a in range(8):
        ja = keyed_neighbour(key, order, k, npix, width, x, y, a)
        if ja >= 0:
            va = uv64(uv, ja) - pc
            na = wp.length(va)
            if na > wp.float64(0.0):
                ua = wp.vec2d(va[0] / na, va[1] / na)
                for b in range(8):
                    jb = keyed_neighbour(key, order, k, npix, width, x, y, b)
                    if jb >= 0:
                        vb = uv64(uv, jb) - pc
                        nb = wp.length(vb)
                        if nb > wp.float64(0.0):
                            cos = ua[0] * (vb[0] / nb) + ua[1] * (vb[1] / nb)
                            if found == 0 or cos < best:
                                best = cos
                                found = 1
                                ba = ja
                                bb = jb
    if found == 0 or best > wp.float64(-0.5):
        ba = -1
        bb = -1
    return wp.vec2i(ba, bb)


@wp.func
def ring_sums(uv: wp.array(dtype=wp.vec2), ring: wp.array(dtype=wp.int32), at_pixel: wp.array(dtype=wp.int32),
              width: int, height: int, k: int, pc: wp.vec2d):
    """(count, sum of x, of y, of x^2, of x y, of y^2) of the offsets from ``pc`` of ring ``k``'s samples in
    the 5x5 pixels around it (the centre's own included), added in ``_ring_directions``' order."""
    cx = int(wp.rint(pc[0]))
    cy = int(wp.rint(pc[1]))
    count = wp.float64(0.0)
    mx = wp.float64(0.0)
    my = wp.float64(0.0)
    sxx = wp.float64(0.0)
    sxy = wp.float64(0.0)
    syy = wp.float64(0.0)
    for dy in range(-2, 3):
        for dx in range(-2, 3):
            j = same_ring_at(at_pixel, ring, width, height, k, cx + dx, cy + dy)
            if j >= 0:
                q = uv64(uv, j) - pc
                count += wp.float64(1.0)
                mx += q[0]
                my += q[1]
                sxx += q[0] * q[0]
                sxy += q[0] * q[1]
                syy += q[1] * q[1]
    return wp.spatial_vectord(count, mx, my, sxx, sxy, syy)


@wp.func
def ring_direction(uv: wp.array(dtype=wp.vec2), ring: wp.array(dtype=wp.int32), at_pixel: wp.array(dtype=wp.int32),
                   width: int, height: int, k: int, pc: wp.vec2d):
    """(whether ring ``k`` has the centre and two more samples in the 5x5 pixels around ``pc``, the unit
    direction of the ring there: the principal axis of those samples' positions): ``_ring_directions``."""
    sums = ring_sums(uv, ring, at_pixel, width, height, k, pc)
    count = sums[0]
    mx = sums[1]
    my = sums[2]
    sxx = sums[3]
    sxy = sums[4]
    syy = sums[5]
    direction = wp.vec2d(wp.float64(1.0), wp.float64(0.0))
    if count >= wp.float64(3.0):
        mx = mx / count
        my = my / count
        cxx = sxx / count - mx * mx
        cxy = sxy / count - mx * my
        cyy = syy / count - my * my
        angle = wp.float64(0.5) * wp.atan2(wp.float64(2.0) * cxy, cxx - cyy)
        direction = wp.vec2d(wp.cos(angle), wp.sin(angle))
    return count >= wp.float64(3.0), direction


@wp.func
def lag_node(uv: wp.array(dtype=wp.vec2), ring: wp.array(dtype=wp.int32), at_pixel: wp.array(dtype=wp.int32),
             width: int, height: int, k: int, pc: wp.vec2d, direction: wp.vec2d, step: int, lag: int):
    """(the sample of ring ``k`` nearest to pc + step * lag * direction among the 5x5 pixels around that
    target and within max(1.5, lag / 2) px of it (-1: none), its signed place along ``direction``):
    ``_lag_nodes``' for one node.

    Size: a @wp.func reading the samples and the pixel lookup directly, plus the ring, the centre's place,
    the ring's direction there, the node's step and the lag."""
    target = pc + wp.float64(float(step * lag)) * direction
    tx = int(wp.rint(target[0]))
    ty = int(wp.rint(target[1]))
    best = wp.float64(1.0e300)
    node = int(-1)
    for dy in range(-2, 3):
        for dx in range(-2, 3):
            j = same_ring_at(at_pixel, ring, width, height, k, tx + dx, ty + dy)
            if j >= 0:
                dist = wp.length(uv64(uv, j) - target)
                if dist < best:
                    best = dist
                    node = j
    if best > wp.max(wp.float64(1.5), wp.float64(0.5 * float(lag))):
        node = -1
    place = wp.float64(0.0)
    if node >= 0:
        place = wp.dot(uv64(uv, node) - pc, direction)
    return node, place


@wp.func
def design_row(du: wp.float64, dv: wp.float64):
    """The quadratic's terms at (du, dv): 1, du, dv, du^2, du dv, dv^2."""
    return VEC6D(wp.float64(1.0), du, dv, du * du, du * dv, dv * dv)


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
def cross_neighbour(at_pixel: wp.array(dtype=wp.int32), ring: wp.array(dtype=wp.int32),
                    depth: wp.array(dtype=wp.float64), var: wp.array(dtype=wp.float64), x: int, y: int, kc: int,
                    off: wp.vec2i, cc: CrossCheck):
    """The sample at ``off`` from pixel (x, y) that a check across rings uses (another ring's, with a
    finite depth and a variance > 0), -1: none."""
    xx = x + off[0]
    yy = y + off[1]
    found = int(-1)
    if xx >= 0 and xx < cc.width and yy >= 0 and yy < cc.height:
        j = at_pixel[yy * cc.width + xx]
        if j >= 0:
            if ring[j] != kc and wp.isfinite(depth[j]) and var[j] > wp.float64(0.0):
                found = j
    return found


@wp.func
def cross_fit(uv: wp.array(dtype=wp.vec2d), depth: wp.array(dtype=wp.float64), var: wp.array(dtype=wp.float64),
              c: int, count: int, limit: wp.float64, store: bool, cc: CrossCheck, row: int,
              nbr: wp.array2d(dtype=wp.int32), res: wp.array2d(dtype=wp.float64), work: wp.array2d(dtype=wp.float64)):
    """One weighted fit of sample c's check (``neighbour_checks._cross_fit``) to its ``count`` neighbours
    nbr[row, :count] whose res[row] is at most ``limit``: (the normal matrix, whether the fit can be made,
    the robust spread of their normalised residuals); with ``store`` their residuals go to res[row] (FAR:
    left out); work[row] holds them for the median."""
    N = MAT66D()
    rhs = VEC6D()
    cnt = int(0)
    for t in range(count):
        if res[row, t] <= limit:
            j = nbr[row, t]
            a = design_row(uv[j][0] - uv[c][0], uv[j][1] - uv[c][1])
            w = wp.float64(1.0) / var[j]
            for p in range(6):
                wa = w * a[p]
                rhs[p] = rhs[p] + wa * depth[j]
                for q in range(p, 6):
                    N[p, q] = N[p, q] + wa * a[q]
            cnt += 1
    for p in range(6):  # the lower triangle: the upper's mirror
        for q in range(p):
            N[p, q] = N[q, p]
    good = cnt >= MIN_CROSS_NEIGHBOURS
    if good:
        good = symmetric_condition(N) < cc.max_cond
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
def check_reach_kernel(
    uv: wp.array(dtype=wp.vec2),
    ring: wp.array(dtype=wp.int32),
    pixel: wp.array(dtype=wp.int32),
    usable: wp.array(dtype=wp.int32),
    key: wp.array(dtype=wp.int64),
    order: wp.array(dtype=wp.int32),
    at_pixel: wp.array(dtype=wp.int32),
    npix: wp.int64,
    width: int,
    i0: int,
    reach: wp.array(dtype=wp.int32),
):
    """The widest check along its ring of sample usable[i0 + tid]: 8, 4 or 2 where it has four
    same-ring nodes near -2k, -k, k, 2k px along the ring's direction there (within the 5x5 pixels
    of each target and max(1.5, k / 2) px of it, their places strictly increasing, two on either
    side), 1 where only its two next neighbours, 0 where neither.

    uv (n,) vec2, ring and pixel (n,) int32 the samples' (pixel: y * width + x); usable (m,) int32 the samples to test; key (m,)
    int64 sorted ring * npix + pixel of the usable samples and order (m,) int32 the sample of each;
    at_pixel (npix,) int32 a usable sample at each pixel (-1: none): read. reach (n,) int32:
    written at the usable samples.

    Size: the samples' three arrays, the two lookups (by ring and pixel, by pixel), the span's i0, one
    array out."""
    c = usable[i0 + wp.tid()]
    k = ring[c]
    height = at_pixel.shape[0] / width
    pc = uv64(uv, c)
    r = int(0)
    # the ring's direction: the principal axis of its samples in the 5x5 pixels around
    has, direction = ring_direction(uv, ring, at_pixel, width, height, k, pc)
    if has:
        # the widest lag first: the first whose four nodes are fine is the reach (the rest not searched)
        for lj in range(3):
            lag = LAGS[2 - lj]
            fine = int(1)
            prev = wp.float64(-1.0e300)
            for s in range(4):
                if fine == 1:
                    node, place = lag_node(uv, ring, at_pixel, width, height, k, pc, direction,
                                           s - 2 + wp.where(s >= 2, 1, 0), lag)  # steps -2, -1, 1, 2
                    if node < 0:
                        fine = 0
                    else:
                        if place <= prev:
                            fine = 0
                        if s == 1 and place >= wp.float64(0.0):
                            fine = 0
                        if s == 2 and place <= wp.float64(0.0):
                            fine = 0
                        prev = place
            if fine == 1 and r == 0:
                r = lag
                break
    if r == 0:  # the 1 px check, at the sample's own pixel
        px = pixel[c]
        r = wp.where(opposite_pair(uv, key, order, k, npix, width, px % width, px / width, c)[0] >= 0, 1, 0)
    reach[c] = r


@wp.kernel
def next_neighbours_kernel(
    uv: wp.array(dtype=wp.vec2),
    ring: wp.array(dtype=wp.int32),
    pixel: wp.array(dtype=wp.int32),
    centre: wp.array(dtype=wp.int32),
    key: wp.array(dtype=wp.int64),
    order: wp.array(dtype=wp.int32),
    npix: wp.int64,
    width: int,
    i0: int,
    pair: wp.array(dtype=wp.vec2i),
):
    """Sample centre[i0 + tid]'s two samples of its ring among its 8 neighbouring pixels most nearly on
    opposite sides, where at least 120 degrees apart (:func:`opposite_pair`; (-1, -1): none).

    uv (n,) vec2, ring and pixel (n,) int32, centre (m,) int32, key (u,) int64 sorted ring * npix + pixel of
    the usable samples and order (u,) int32 the sample of each: read. pair (m,) vec2i: written.

    Size: the samples' three arrays, the centres, the ring index (keys, their samples, its stride), the
    camera's width, the span's i0, one array out."""
    i = i0 + wp.tid()
    c = centre[i]
    pair[i] = opposite_pair(uv, key, order, ring[c], npix, width, pixel[c] % width, pixel[c] / width, c)


@wp.kernel
def ring_sums_kernel(
    uv: wp.array(dtype=wp.vec2),
    ring: wp.array(dtype=wp.int32),
    centre: wp.array(dtype=wp.int32),
    at_pixel: wp.array(dtype=wp.int32),
    width: int,
    i0: int,
    sums: wp.array(dtype=wp.spatial_vectord),
):
    """Sample centre[i0 + tid]'s :func:`ring_sums` (the host turns them into the ring's direction with
    NumPy's own arctan2, cos and sin, as ``_ring_directions`` does).

    uv (n,) vec2, ring (n,) int32, centre (m,) int32, at_pixel (npix,) int32: read. sums (m,) spatial_vectord:
    written."""
    i = i0 + wp.tid()
    c = centre[i]
    sums[i] = ring_sums(uv, ring, at_pixel, width, at_pixel.shape[0] / width, ring[c], uv64(uv, c))


@wp.kernel
def lag_nodes_kernel(
    uv: wp.array(dtype=wp.vec2),
    ring: wp.array(dtype=wp.int32),
    centre: wp.array(dtype=wp.int32),
    direction: wp.array(dtype=wp.vec2d),
    at_pixel: wp.array(dtype=wp.int32),
    width: int,
    lags: int,
    i0: int,
    nodes: wp.array2d(dtype=wp.int32),
    place: wp.array2d(dtype=wp.float64),
):
    """Sample centre[i0 + tid]'s four same-ring nodes near -2k, -k, k, 2k px along ``direction`` for each of
    the first ``lags`` of ``LAGS``, and their places (:func:`lag_node`; ``_lag_nodes``).

    uv (n,) vec2, ring (n,) int32, centre (m,) int32, direction (m,) vec2d, at_pixel (npix,) int32 a usable
    sample at each pixel (-1: none): read. nodes (m, 4 lags) int32 (-1: none), place (m, 4 lags) float64:
    written.

    Size: the samples' two arrays, the centres and their directions, the pixel lookup, the camera's width,
    the lags, the span's i0, two arrays out."""
    i = i0 + wp.tid()
    c = centre[i]
    height = at_pixel.shape[0] / width
    pc = uv64(uv, c)
    for li in range(lags):
        for s in range(4):
            node, pl = lag_node(uv, ring, at_pixel, width, height, ring[c], pc, direction[i],
                                s - 2 + wp.where(s >= 2, 1, 0), LAGS[li])
            nodes[i, 4 * li + s] = node
            place[i, 4 * li + s] = pl


@wp.kernel
def cross_check_kernel(
    at_pixel: wp.array(dtype=wp.int32),
    ring: wp.array(dtype=wp.int32),
    pixel: wp.array(dtype=wp.int32),
    uv: wp.array(dtype=wp.vec2d),
    depth: wp.array(dtype=wp.float64),
    var: wp.array(dtype=wp.float64),
    offsets: wp.array(dtype=wp.vec2i),
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
    other rings at ``offsets`` fit, weighted by 1 / var, refitted without the neighbours beyond
    ``cc.reject`` robust spreads (``neighbour_checks._cross_ring_checks``, the NumPy statement):
    made[i] = 1 where the check is made (neighbours of an inner and an outer ring, three rings in
    all, at least three a term, a condition number under ``cc.max_cond``, a spread within
    ``cc.gate``), r[i] its residual and v[i] its predicted variance.

    at_pixel (npix,) int32 the sample at each pixel (-1: none); ring, pixel (n,) int32; uv (n,) vec2d;
    depth, var (n,) float64; offsets (K,) vec2i; centre (m,) int32: read. nbr (m, K) int32, res, work
    (m, K) float64: scratch (a centre's neighbours, found once, and their residuals). made (m,) int32,
    r, v (m,) float64: written.

    Size: the view's index and per-sample arrays, the offsets, the centres and settings, the span's
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
    for o in range(offsets.shape[0]):  # the neighbours, once: the fits read them from nbr[i]
        j = cross_neighbour(at_pixel, ring, depth, var, x, y, kc, offsets[o], cc)
        if j >= 0:
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


def sample_reach(uv: wp.array, ring: wp.array, pixel: wp.array, usable: np.ndarray, *, width: int,
                 threads: int | None = None) -> np.ndarray:
    """(n,) int32 each sample's widest check along its ring (:func:`check_reach_kernel`): 8, 4,
    2, 1 or 0; -1 where not ``usable``.

    Args:
        uv: (n,) vec2 the samples' camera positions (px).
        ring, pixel: (n,) int32 their rings and camera pixels (y * width + x).
        usable: (n,) bool the samples to check and to check against (a finite depth).
        width: camera width (px).
        threads: CPU threads; default all cores.
    """
    fn = "sample_reach"
    n = check_array("uv", uv, None, wp.vec2, fn)
    check_array("ring", ring, n, wp.int32, fn)
    check_array("pixel", pixel, n, wp.int32, fn)
    usable = np.asarray(usable, bool)
    if usable.shape != (n,):
        raise ValueError(f"{fn}: usable must be ({n},) bool, got {usable.shape}")
    reach = np.full(n, -1, np.int32)
    use = np.flatnonzero(usable)
    if use.size == 0:
        return reach
    dev = uv.device
    px = pixel.numpy().astype(np.int64)
    rg = ring.numpy().astype(np.int64)
    npix = int(px[use].max()) + int(width) + 2  # more than any pixel: the key's stride per ring
    key = rg[use] * npix + px[use]
    o = np.argsort(key, kind="stable")
    at_pixel = np.full(npix, -1, np.int32)
    at_pixel[px[use]] = use  # of two rings' samples at one pixel, one (as the NumPy index keeps it)
    out = wp.array(reach, dtype=wp.int32, device=dev)
    args = [uv, ring, pixel, wp.array(use.astype(np.int32), dtype=wp.int32, device=dev),
            wp.array(key[o], dtype=wp.int64, device=dev), wp.array(use[o].astype(np.int32), dtype=wp.int32, device=dev),
            wp.array(at_pixel, dtype=wp.int32, device=dev), wp.int64(npix), int(width)]
    launch_spans(check_reach_kernel, use.size, lambda i0: args + [i0], [out], dev,
                 default_threads() if threads is None else threads, min_span=1024)
    return out.numpy()


def ring_lag_nodes(uv: np.ndarray, ring: np.ndarray, at_pixel: np.ndarray, centre: np.ndarray, *, width: int,
                   lags: int, threads: int | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(the ``centre`` samples whose ring has a direction there (k,), that direction (k, 2), their nodes
    (k, lags, 4) int64 (-1: none) and the nodes' places (k, lags, 4) float64) for the first ``lags`` of
    (2, 4, 8) px: ``neighbour_checks._ring_directions`` and ``_lag_nodes``, the same samples, directions
    and places to the bit (the positions' sums by :func:`ring_sums_kernel`, the direction from them by
    NumPy as there, the nodes by :func:`lag_nodes_kernel`).

    Args:
        uv: (n, 2) float the samples' camera positions (float32 values, as the samples hold them).
        ring: (n,) int each sample's ring.
        at_pixel: (H * W,) int a usable sample's index at each camera pixel (-1: none).
        centre: (m,) int the samples to find nodes for.
        width: camera width (px).
        lags: how many of the lags (1..3).
        threads: CPU threads; default all cores.
    """
    if not 1 <= lags <= 3:
        raise ValueError(f"ring_lag_nodes: lags must be 1..3, got {lags}")
    centre = np.asarray(centre, np.int64)
    dev, threads = "cpu", default_threads() if threads is None else threads
    uv32 = wp.array(np.ascontiguousarray(np.asarray(uv).reshape(-1, 2), np.float32), dtype=wp.vec2, device=dev)
    ring_w = wp.array(np.asarray(ring, np.int32), dtype=wp.int32, device=dev)
    at_w = wp.array(np.asarray(at_pixel, np.int32), dtype=wp.int32, device=dev)
    sums = np.zeros((centre.size, 6))
    if centre.size:
        c_w = wp.array(centre.astype(np.int32), dtype=wp.int32, device=dev)
        launch_spans(ring_sums_kernel, centre.size, lambda i0: [uv32, ring_w, c_w, at_w, int(width), i0],
                     [wp.array(sums, dtype=wp.spatial_vectord, device=dev, copy=False)], dev, threads, min_span=1024)
        wp.synchronize_device(dev)
    # _ring_directions' arithmetic on the sums
    count, mean, cov = sums[:, 0], sums[:, 1:3].copy(), sums[:, 3:6]
    keep = count >= 3
    n = np.maximum(count, 1)[:, None]
    mean /= n
    cxx, cxy, cyy = (cov / n).T
    cxx, cxy, cyy = cxx - mean[:, 0] ** 2, cxy - mean[:, 0] * mean[:, 1], cyy - mean[:, 1] ** 2
    angle = 0.5 * np.arctan2(2 * cxy, cxx - cyy)
    direction = np.stack([np.cos(angle), np.sin(angle)], 1)[keep]
    kept = centre[keep]
    nodes = np.full((kept.size, 4 * lags), -1, np.int32)
    place = np.zeros((kept.size, 4 * lags), np.float64)
    if kept.size:
        args = [uv32, ring_w, wp.array(kept.astype(np.int32), dtype=wp.int32, device=dev),
                wp.array(np.ascontiguousarray(direction), dtype=wp.vec2d, device=dev), at_w, int(width), int(lags)]
        launch_spans(lag_nodes_kernel, kept.size, lambda i0: args + [i0],
                     [wp.array(nodes, dtype=wp.int32, device=dev, copy=False),
                      wp.array(place, dtype=wp.float64, device=dev, copy=False)], dev, threads, min_span=1024)
        wp.synchronize_device(dev)
    return kept, direction, nodes.reshape(-1, lags, 4).astype(np.int64), place.reshape(-1, lags, 4)


def next_neighbours(uv: np.ndarray, ring: np.ndarray, pixel: np.ndarray, key: np.ndarray, order: np.ndarray,
                    npix: int, centre: np.ndarray, *, width: int,
                    threads: int | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(c, a, b): the ``centre`` samples with two samples of their ring among their 8 neighbouring pixels
    at least 120 degrees apart, and those two (:func:`next_neighbours_kernel`; the NumPy statement
    ``neighbour_checks._next_neighbours``, the same samples). ``key``/``order``/``npix``: the ring index
    (``neighbour_checks._RingIndex``); ``uv`` (n, 2) float32 values, ``ring``, ``pixel`` (n,) int.

    Size: the samples' three arrays, the ring index's three parts, the centres, the camera's width and the
    threads."""
    centre = np.asarray(centre, np.int64)
    pair = np.full((centre.size, 2), -1, np.int32)
    if centre.size:
        dev = "cpu"
        args = [wp.array(np.ascontiguousarray(np.asarray(uv).reshape(-1, 2), np.float32), dtype=wp.vec2, device=dev),
                wp.array(np.asarray(ring, np.int32), dtype=wp.int32, device=dev),
                wp.array(np.asarray(pixel, np.int32), dtype=wp.int32, device=dev),
                wp.array(centre.astype(np.int32), dtype=wp.int32, device=dev),
                wp.array(np.asarray(key, np.int64), dtype=wp.int64, device=dev),
                wp.array(np.asarray(order, np.int32), dtype=wp.int32, device=dev), wp.int64(npix), int(width)]
        launch_spans(next_neighbours_kernel, centre.size, lambda i0: args + [i0],
                     [wp.array(pair, dtype=wp.vec2i, device=dev, copy=False)], dev,
                     default_threads() if threads is None else threads, min_span=1024)
        wp.synchronize_device(dev)
    use = pair[:, 0] >= 0
    return centre[use], pair[use, 0].astype(np.int64), pair[use, 1].astype(np.int64)


def cross_ring_checks(depth: wp.array, var: wp.array, uv: wp.array, ring: wp.array, pixel: wp.array,
                      at_pixel: wp.array, centre: np.ndarray, *, radius: int, width: int, reject: float,
                      gate: float, threads: int | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(checked samples (k,) int64, r (k,), predicted variance (k,)) of :func:`cross_check_kernel`
    for the ``centre`` samples, in their order: the checks of the NumPy statement
    (``neighbour_checks._cross_ring_checks``), the same samples where no threshold's test falls
    within rounding and their numbers to ~1e-7 of r and ~1e-12 of the variance (its solves are
    LAPACK's, these the kernel's).

    Args:
        depth, var: (n,) float64 each sample's depth (NaN: not placed) and its predicted variance.
        uv: (n,) vec2d camera positions (px). ring, pixel: (n,) int32 rings and pixels (y * width + x).
        at_pixel: (npix,) int32 the sample at each pixel (-1: none); npix // width rows are looked in.
        centre: (m,) the samples to check. radius: the neighbourhood (px). width: camera width.
        reject, gate: ``neighbour_checks.CROSS_REJECT`` and ``CROSS_GATE``.
        threads: CPU threads; default all cores.

    Size: the view's six arrays (made once for every call of a view), the centres, the
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
    off = np.array([(dx, dy) for dy in range(-rad, rad + 1) for dx in range(-rad, rad + 1)
                    if 0 < dx * dx + dy * dy <= rad * rad], np.int32).reshape(-1, 2)
    cc = CrossCheck()
    cc.width = int(width)
    cc.height = int(at_pixel.shape[0] // width)
    cc.reject = float(reject)
    cc.gate = float(gate)
    cc.max_cond = 1e12
    k = off.shape[0]
    nbr = wp.empty((m, k), dtype=wp.int32, device=dev)
    res = wp.empty((m, k), dtype=wp.float64, device=dev)
    work = wp.empty((m, k), dtype=wp.float64, device=dev)
    made = wp.empty(m, dtype=wp.int32, device=dev)
    r = wp.empty(m, dtype=wp.float64, device=dev)
    v = wp.empty(m, dtype=wp.float64, device=dev)
    args = [at_pixel, ring, pixel, uv, depth, var, wp.array(off, dtype=wp.vec2i, device=dev),
            wp.array(centre.astype(np.int32), dtype=wp.int32, device=dev), cc]
    launch_spans(cross_check_kernel, m, lambda i0: args + [i0], [nbr, res, work, made, r, v], dev,
                 default_threads() if threads is None else threads, min_span=64)
    ok = made.numpy().astype(bool)
    return centre[ok], r.numpy()[ok], v.numpy()[ok]
