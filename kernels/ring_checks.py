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

__all__ = ["check_reach_kernel", "next_neighbours_kernel", "ring_sums_kernel", "lag_nodes_kernel", "sample_reach", "pixel_offsets",
           "next_neighbours", "ring_lag_nodes"]

# no gradients here, and loops left as loops: unrolled (Warp's default for short constant
# ranges), the 3 lags x 4 nodes x 5 x 5 pixels took minutes to compile on the CPU
wp.set_module_options({"enable_backward": False, "max_unroll": 1})

LAGS = wp.constant(wp.vec3i(2, 4, 8))
"""The checks wider than 1 px (``neighbour_checks.NEIGHBOUR_LAGS[1:]``)."""
VEC8I = wp.types.vector(length=8, dtype=wp.int32)
VEC8D = wp.types.vector(length=8, dtype=wp.float64)

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
def keyed_neighbour(key: wp.array(dtype=wp.int64), order: wp.array(dtype=wp.int32),
                    at_pixel: wp.array(dtype=wp.int32), k: int, npix: wp.int64, width: int, x: int, y: int, a: int):
    """The sample of ring ``k`` at the a-th of the 8 pixels around (x, y) (row by row, the centre left out;
    -1: none there).

    Size: a @wp.func reading the ring index's three arrays directly, plus the ring, the index's stride, the
    camera's width, the pixel and which of its neighbours."""
    ia = a + wp.where(a >= 4, 1, 0)
    ax = x + ia % 3 - 1
    ay = y + ia / 3 - 1
    j = int(-1)
    if ax >= 0 and ax < width and ay >= 0:
        # a pixel with no sample of any ring needs no search (one with one may hold two of a ring: the key
        # decides which)
        if at_pixel[ay * width + ax] >= 0:
            j = keyed_sample(key, order, wp.int64(k) * npix + wp.int64(ay * width + ax))
    return j


@wp.func
def opposite_pair(uv: wp.array(dtype=wp.vec2), key: wp.array(dtype=wp.int64), order: wp.array(dtype=wp.int32),
                  at_pixel: wp.array(dtype=wp.int32), k: int, npix: wp.int64, width: int, x: int, y: int, c: int):
    """The two samples of ring ``k`` among the 8 pixels around (x, y) most nearly on opposite sides of sample
    ``c`` (the pair of least cosine between their unit offsets, the first such in the 8 x 8 order, both with
    an offset), where at least 120 degrees apart; (-1, -1): none (``_next_neighbours``' test and choice).

    Size: a @wp.func reading the samples and the ring index directly, plus the ring, the index's stride,
    the pixel and the sample."""
    pc = uv64(uv, c)
    # each neighbour looked up once (a binary search of the key each), its unit offset kept: the 8 x 8 pairs
    # then read them (the same pairs, order and tie-break as looking each up inside the pair loop)
    nbr = VEC8I()
    ux = VEC8D()
    uy = VEC8D()
    for a in range(8):
        ja = keyed_neighbour(key, order, at_pixel, k, npix, width, x, y, a)
        if ja >= 0:
            va = uv64(uv, ja) - pc
            na = wp.length(va)
            if na > wp.float64(0.0):
                ux[a] = va[0] / na
                uy[a] = va[1] / na
            else:
                ja = -1
        nbr[a] = ja
    best = wp.float64(1.0e308)
    found = int(0)
    ba = int(-1)
    bb = int(-1)
    for a in range(8):
        if nbr[a] >= 0:
            for b in range(8):
                if nbr[b] >= 0:
                    cos = ux[a] * ux[b] + uy[a] * uy[b]
                    if found == 0 or cos < best:
                        best = cos
                        found = 1
                        ba = nbr[a]
                        bb = nbr[b]
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
             width: int, height: int, k: int, pc: wp.vec2d, direction: wp.vec2d, step: int, lag: int,
             offsets: wp.vec4d):
    """(the sample of ring ``k`` nearest to pc + step * lag * direction among the 5x5 pixels around that
    target and within max(1.5, lag / 2) px of it (-1: none), its signed place along ``direction``):
    ``_lag_nodes``' for one node.

    The 3 x 3 pixels around the target are read first: ``offsets`` (lo_x, hi_x, lo_y, hi_y) bound where a
    sample lies in the pixel that holds it (x + lo_x .. x + hi_x; :func:`pixel_offsets`), so a sample of the
    outer 16 pixels is at least as far as their nearest side, and a nearer one found inside is the nearest;
    otherwise all 25 are read in their order, as before (the same node, ties included).

    Size: a @wp.func reading the samples and the pixel lookup directly, plus the ring, the centre's place,
    the ring's direction there, the node's step and the lag, the samples' offset bounds."""
    target = pc + wp.float64(float(step * lag)) * direction
    tx = int(wp.rint(target[0]))
    ty = int(wp.rint(target[1]))
    best = wp.float64(1.0e300)
    node = int(-1)
    for dy in range(-1, 2):
        for dx in range(-1, 2):
            j = same_ring_at(at_pixel, ring, width, height, k, tx + dx, ty + dy)
            if j >= 0:
                dist = wp.length(uv64(uv, j) - target)
                if dist < best:
                    best = dist
                    node = j
    # the outer pixels' nearest side: columns tx -+ 2, rows ty -+ 2 (a margin for the distances' rounding)
    fx = target[0] - wp.float64(float(tx))
    fy = target[1] - wp.float64(float(ty))
    two = wp.float64(2.0)
    outer = wp.min(wp.min(fx + two - offsets[1], two + offsets[0] - fx), wp.min(fy + two - offsets[3], two + offsets[2] - fy))
    if not (best < outer * wp.float64(0.999999) - wp.float64(1.0e-9)):
        # (the 3 x 3 loop above written out again for 5 x 5: one helper taking the window's size measured 42 ms
        # a full-size view against 36.7, one loop over both windows 44.6: Warp's CPU code does not specialise it)
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
    offsets: wp.vec4d,
    i0: int,
    reach: wp.array(dtype=wp.int32),
):
    """The widest check along its ring of sample usable[i0 + tid]: 8, 4 or 2 where it has four
    same-ring nodes near -2k, -k, k, 2k px along the ring's direction there (within the 5x5 pixels
    of each target and max(1.5, k / 2) px of it, their places strictly increasing, two on either
    side), 1 where only its two next neighbours, 0 where neither.

    uv (n,) vec2, ring and pixel (n,) int32 the samples' (pixel: y * width + x); usable (m,) int32 the samples to test; key (m,)
    int64 sorted ring * npix + pixel of the usable samples and order (m,) int32 the sample of each;
    at_pixel (npix,) int32 a usable sample at each pixel (-1: none); offsets their bounds in their pixels
    (:func:`pixel_offsets`): read. reach (n,) int32: written at the usable samples.

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
                                           s - 2 + wp.where(s >= 2, 1, 0), lag, offsets)  # steps -2, -1, 1, 2
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
        r = wp.where(opposite_pair(uv, key, order, at_pixel, k, npix, width, px % width, px / width, c)[0] >= 0, 1, 0)
    reach[c] = r


@wp.kernel
def next_neighbours_kernel(
    uv: wp.array(dtype=wp.vec2),
    ring: wp.array(dtype=wp.int32),
    pixel: wp.array(dtype=wp.int32),
    centre: wp.array(dtype=wp.int32),
    key: wp.array(dtype=wp.int64),
    order: wp.array(dtype=wp.int32),
    at_pixel: wp.array(dtype=wp.int32),
    npix: wp.int64,
    width: int,
    i0: int,
    pair: wp.array(dtype=wp.vec2i),
):
    """Sample centre[i0 + tid]'s two samples of its ring among its 8 neighbouring pixels most nearly on
    opposite sides, where at least 120 degrees apart (:func:`opposite_pair`; (-1, -1): none).

    uv (n,) vec2, ring and pixel (n,) int32, centre (m,) int32, key (u,) int64 sorted ring * npix + pixel of
    the usable samples and order (u,) int32 the sample of each, at_pixel (npix,) int32 a usable sample at
    each pixel (-1: none): read. pair (m,) vec2i: written.

    Size: the samples' three arrays, the centres, the ring index (keys, their samples, the pixel lookup, its
    stride), the camera's width, the span's i0, one array out."""
    i = i0 + wp.tid()
    c = centre[i]
    pair[i] = opposite_pair(uv, key, order, at_pixel, ring[c], npix, width, pixel[c] % width, pixel[c] / width, c)


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
    first: int,
    lags: int,
    offsets: wp.vec4d,
    i0: int,
    nodes: wp.array2d(dtype=wp.int32),
    place: wp.array2d(dtype=wp.float64),
):
    """Sample centre[i0 + tid]'s four same-ring nodes near -2k, -k, k, 2k px along ``direction`` for each of
    ``lags`` of ``LAGS`` from its ``first``, and their places (:func:`lag_node`; ``_lag_nodes``).

    uv (n,) vec2, ring (n,) int32, centre (m,) int32, direction (m,) vec2d, at_pixel (npix,) int32 a usable
    sample at each pixel (-1: none), offsets their bounds in their pixels (:func:`pixel_offsets`): read. nodes (m, 4 lags) int32 (-1: none), place (m, 4 lags) float64:
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
                                s - 2 + wp.where(s >= 2, 1, 0), LAGS[first + li], offsets)
            nodes[i, 4 * li + s] = node
            place[i, 4 * li + s] = pl


# ----------------------------------------------------------------------------- host


def pixel_offsets(uv: np.ndarray, pixel: np.ndarray, width: int) -> wp.vec4d:
    """(lo_x, hi_x, lo_y, hi_y): where samples lie in their pixels, x + lo_x .. x + hi_x (``uv`` (n, 2) their
    float32 positions, read as the kernels read them; ``pixel`` (n,) y * width + x): the bounds by which
    :func:`lag_node` settles a node from the 3 x 3 pixels. Given the samples a pixel lookup may hold (or more:
    wider bounds only read more pixels). Edge samples lie 0..1 px from their pixel's corner, others elsewhere:
    each view's own."""
    pixel = np.asarray(pixel, np.int64)
    if pixel.size == 0:
        return wp.vec4d(0.0, 0.0, 0.0, 0.0)
    at = np.asarray(uv, np.float32).reshape(-1, 2).astype(np.float64)
    ox, oy = at[:, 0] - (pixel % int(width)), at[:, 1] - (pixel // int(width))
    return wp.vec4d(float(ox.min()), float(ox.max()), float(oy.min()), float(oy.max()))


def _held_offsets(uv: np.ndarray, at_pixel: np.ndarray, width: int) -> wp.vec4d:
    p = np.flatnonzero(np.asarray(at_pixel) >= 0)
    return pixel_offsets(np.asarray(uv).reshape(-1, 2)[np.asarray(at_pixel)[p]], p, width)


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
            wp.array(at_pixel, dtype=wp.int32, device=dev), wp.int64(npix), int(width),
            pixel_offsets(uv.numpy()[use], px[use], int(width))]
    launch_spans(check_reach_kernel, use.size, lambda i0: args + [i0], [out], dev,
                 default_threads() if threads is None else threads, min_span=1024)
    return out.numpy()


def _host_out(a: np.ndarray, dtype, dev) -> wp.array:
    """A kernel's output over the host array ``a`` (its initial values): ``a``'s own memory on the CPU, a
    copy on another device (:func:`_read_back` brings it back)."""
    return wp.array(a, dtype=dtype, device=dev, copy=not dev.is_cpu)


def _read_back(out: wp.array, a: np.ndarray) -> np.ndarray:
    """``a`` with the kernel's results in ``out`` (:func:`_host_out`): ``a`` itself on the CPU (once the
    device is done), the device's values read back elsewhere."""
    wp.synchronize_device(out.device)
    return a if out.device.is_cpu else out.numpy().reshape(a.shape)


def ring_lag_nodes(uv: np.ndarray, ring: np.ndarray, at_pixel: np.ndarray, centre: np.ndarray, *, width: int,
                   lags: tuple, offsets: wp.vec4d | None = None, threads: int | None = None,
                   device="cpu") -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(the ``centre`` samples whose ring has a direction there (k,), that direction (k, 2), their nodes
    (k, len(lags), 4) int64 (-1: none) and the nodes' places (k, len(lags), 4) float64) for ``lags`` of
    (2, 4, 8) px: ``neighbour_checks._ring_directions`` and ``_lag_nodes``, the same samples, directions
    and places to the bit (the positions' sums by :func:`ring_sums_kernel`, the direction from them by
    NumPy as there, the nodes by :func:`lag_nodes_kernel`).

    Args:
        uv: (n, 2) float the samples' camera positions (float32 values, as the samples hold them).
        ring: (n,) int each sample's ring.
        at_pixel: (H * W,) int a usable sample's index at each camera pixel (-1: none).
        centre: (m,) int the samples to find nodes for.
        width: camera width (px).
        lags: the lags (px), in order, without a gap: (2,), (4, 8), (2, 4, 8), ...
        offsets: :func:`pixel_offsets` of the samples ``at_pixel`` holds, where the caller has them (None: read
            from ``at_pixel``, a pass over every pixel).
        threads: CPU threads; default all cores.
        device: where the kernels run (the view's device; NumPy in and out).
    """
    every = tuple(int(k) for k in LAGS)
    lags = tuple(int(k) for k in lags)
    if not lags or lags[0] not in every or every[every.index(lags[0]):][:len(lags)] != lags:
        raise ValueError(f"ring_lag_nodes: lags must be a run of {every}, got {lags}")
    first, lags = every.index(lags[0]), len(lags)
    centre = np.asarray(centre, np.int64)
    dev, threads = wp.get_device(device), default_threads() if threads is None else threads
    uv32 = wp.array(np.ascontiguousarray(np.asarray(uv).reshape(-1, 2), np.float32), dtype=wp.vec2, device=dev)
    ring_w = wp.array(np.asarray(ring, np.int32), dtype=wp.int32, device=dev)
    at_w = wp.array(np.asarray(at_pixel, np.int32), dtype=wp.int32, device=dev)
    sums = np.zeros((centre.size, 6))
    if centre.size:
        c_w = wp.array(centre.astype(np.int32), dtype=wp.int32, device=dev)
        out = _host_out(sums, wp.spatial_vectord, dev)
        launch_spans(ring_sums_kernel, centre.size, lambda i0: [uv32, ring_w, c_w, at_w, int(width), i0], [out],
                     dev, threads, min_span=1024)
        sums = _read_back(out, sums)
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
                wp.array(np.ascontiguousarray(direction), dtype=wp.vec2d, device=dev), at_w, int(width), first, lags,
                offsets if offsets is not None else _held_offsets(uv, at_pixel, int(width))]
        outs = [_host_out(nodes, wp.int32, dev), _host_out(place, wp.float64, dev)]
        launch_spans(lag_nodes_kernel, kept.size, lambda i0: args + [i0], outs, dev, threads, min_span=1024)
        nodes, place = _read_back(outs[0], nodes), _read_back(outs[1], place)
    return kept, direction, nodes.reshape(-1, lags, 4).astype(np.int64), place.reshape(-1, lags, 4)


def next_neighbours(uv: np.ndarray, ring: np.ndarray, pixel: np.ndarray, key: np.ndarray, order: np.ndarray,
                    at_pixel: np.ndarray, npix: int, centre: np.ndarray, *, width: int,
                    threads: int | None = None, device="cpu") -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(c, a, b): the ``centre`` samples with two samples of their ring among their 8 neighbouring pixels
    at least 120 degrees apart, and those two (:func:`next_neighbours_kernel`; the NumPy statement
    ``neighbour_checks._next_neighbours``, the same samples). ``key``/``order``/``at_pixel``/``npix``: the ring
    index (``neighbour_checks._RingIndex``); ``uv`` (n, 2) float32 values, ``ring``, ``pixel`` (n,) int;
    ``device``: where the kernel runs (NumPy in and out).

    Size: the samples' three arrays, the ring index's four parts, the centres, the camera's width, the
    threads and the device."""
    centre = np.asarray(centre, np.int64)
    pair = np.full((centre.size, 2), -1, np.int32)
    if centre.size:
        dev = wp.get_device(device)
        args = [wp.array(np.ascontiguousarray(np.asarray(uv).reshape(-1, 2), np.float32), dtype=wp.vec2, device=dev),
                wp.array(np.asarray(ring, np.int32), dtype=wp.int32, device=dev),
                wp.array(np.asarray(pixel, np.int32), dtype=wp.int32, device=dev),
                wp.array(centre.astype(np.int32), dtype=wp.int32, device=dev),
                wp.array(np.asarray(key, np.int64), dtype=wp.int64, device=dev),
                wp.array(np.asarray(order, np.int32), dtype=wp.int32, device=dev),
                wp.array(np.asarray(at_pixel, np.int32), dtype=wp.int32, device=dev), wp.int64(npix), int(width)]
        out = _host_out(pair, wp.vec2i, dev)
        launch_spans(next_neighbours_kernel, centre.size, lambda i0: args + [i0], [out], dev,
                     default_threads() if threads is None else threads, min_span=1024)
        pair = _read_back(out, pair)
    use = pair[:, 0] >= 0
    return centre[use], pair[use, 0].astype(np.int64), pair[use, 1].astype(np.int64)
