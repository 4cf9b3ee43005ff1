"""Generic per-item moves on the device: the finite items of an array (flags, and their indices:
count, scan, write), a pixel map's occupied pixels in row order (``pixel_rows``), a gather by index, a value set at indices, a histogram of small integer values
(one row of counts a span, the rows summed on the host: the counts, not the items, are read), and
order statistics (a radix sort on the device, the few values they need read: ``median`` and
``percentiles`` as NumPy's give them)."""

from __future__ import annotations

from typing import Any

import numpy as np
import warp as wp

from ringscan.kernels.launch import check_array, default_threads, launch_spans, scan_counts

wp.set_module_options({"enable_backward": False})  # no gradients are taken here: no adjoint code to compile

__all__ = ["finite_flags", "finite_indices", "nonzero_indices", "gather", "set_at", "count_values", "median",
           "median64", "percentiles", "percentile32", "sort_finite", "pixel_rows"]

SPAN = wp.constant(4096)
"""Items a histogram row counts (one thread a row)."""


# ----------------------------------------------------------------------------- kernels


@wp.kernel
def flag_finite_kernel(a: wp.array(dtype=wp.float32), i0: int, flags: wp.array(dtype=wp.int32)):
    """flags[i] = 1 where a[i] is finite. a (n,) float32: read; flags (n,) int32: written."""
    i = i0 + wp.tid()
    flags[i] = wp.where(wp.isfinite(a[i]), 1, 0)


@wp.kernel
def flag_nonzero_kernel(values: wp.array(dtype=wp.int32), i0: int, flags: wp.array(dtype=wp.int32)):
    """flags[i] = 1 where values[i] != 0. values (n,) int32: read; flags (n,) int32: written."""
    i = i0 + wp.tid()
    flags[i] = wp.where(values[i] != 0, 1, 0)


@wp.kernel
def write_indices_kernel(flags: wp.array(dtype=wp.int32), offsets: wp.array(dtype=wp.int32), i0: int,
                         out: wp.array(dtype=wp.int32)):
    """out[offsets[i]] = i where flags[i]. flags, offsets (n,) int32: read; out (count,) int32: written."""
    i = i0 + wp.tid()
    if flags[i] != 0:
        out[offsets[i]] = i


@wp.kernel
def occupied_kernel(at_pixel: wp.array(dtype=wp.int32), n: int, flag: wp.array(dtype=wp.int32)):
    """flag[p] = 1 where pixel p holds an item (0 <= at_pixel[p] < n), else 0; flag's last entry (one past
    the pixels) stays 0. at_pixel (npix,) int32: read; flag (npix + 1,) int32: written."""
    p = wp.tid()
    j = at_pixel[p]
    flag[p] = wp.where(j >= 0 and j < n, 1, 0)


@wp.kernel
def occupied_list_kernel(at_pixel: wp.array(dtype=wp.int32), n: int, rank: wp.array(dtype=wp.int32),
                         listed: wp.array(dtype=wp.int32)):
    """listed[rank[p]] = at_pixel[p] at every pixel holding an item: the items in pixel order. at_pixel
    (npix,), rank (npix + 1,) int32 (the occupied pixels before each): read; listed (n,) int32 (its first
    rank[npix]): written."""
    p = wp.tid()
    j = at_pixel[p]
    if j >= 0 and j < n:
        listed[rank[p]] = j


@wp.kernel
def gather_kernel(src: wp.array(dtype=Any), index: wp.array(dtype=wp.int32), i0: int, out: wp.array(dtype=Any)):
    """out[j] = src[index[j]]. src (n,), index (m,) int32: read; out (m,): written."""
    j = i0 + wp.tid()
    out[j] = src[index[j]]


for _t in (wp.float32, wp.float64, wp.int32, wp.vec2, wp.vec3, wp.vec4):
    wp.overload(gather_kernel, {"src": wp.array(dtype=_t), "out": wp.array(dtype=_t)})


@wp.kernel
def set_at_kernel(index: wp.array(dtype=wp.int32), value: int, i0: int, a: wp.array(dtype=wp.int32)):
    """a[index[j]] = value. index (m,) int32: read; a (n,) int32: written at the indices."""
    a[index[i0 + wp.tid()]] = value


@wp.kernel
def count_values_kernel(values: wp.array(dtype=wp.int32), bins: int, i0: int, counts: wp.array2d(dtype=wp.int32)):
    """Row i0 + tid of ``counts``: how often each of 0 .. bins - 1 occurs among values[row * SPAN, (row + 1) *
    SPAN) (others not counted). values (n,) int32: read; counts (rows, bins) int32: written."""
    r = i0 + wp.tid()
    for b in range(bins):
        counts[r, b] = 0
    end = wp.min((r + 1) * SPAN, values.shape[0])
    for i in range(r * SPAN, end):
        v = values[i]
        if v >= 0 and v < bins:
            counts[r, v] = counts[r, v] + 1


# ----------------------------------------------------------------------------- host


def finite_flags(a: wp.array, *, threads: int | None = None) -> wp.array:
    """(n,) int32 1 where ``a`` ((n,) float32) is finite, else 0, on a's device."""
    n = check_array("a", a, None, wp.float32, "finite_flags")
    flags = wp.empty(n, dtype=wp.int32, device=a.device)
    launch_spans(flag_finite_kernel, n, lambda i0: [a, i0], [flags], a.device,
                 default_threads() if threads is None else threads)
    return flags


def nonzero_indices(flags: wp.array, *, threads: int | None = None) -> wp.array:
    """(m,) int32 the indices where ``flags`` ((n,) int32) is not 0, in order, on its device (count,
    scan, write: one read, the count)."""
    n = check_array("flags", flags, None, wp.int32, "nonzero_indices")
    dev = flags.device
    ones = wp.empty(n, dtype=wp.int32, device=dev)
    threads = default_threads() if threads is None else threads
    launch_spans(flag_nonzero_kernel, n, lambda i0: [flags, i0], [ones], dev, threads)
    offsets, total = scan_counts(ones)
    out = wp.empty(total, dtype=wp.int32, device=dev)
    if total:
        launch_spans(write_indices_kernel, n, lambda i0: [ones, offsets, i0], [out], dev, threads)
    return out


def finite_indices(a: wp.array, *, threads: int | None = None) -> wp.array:
    """(m,) int32 the indices of ``a``'s ((n,) float32) finite values, in order, on a's device
    (count, scan, write: one read, the count)."""
    check_array("a", a, None, wp.float32, "finite_indices")
    return nonzero_indices(finite_flags(a, threads=threads), threads=threads)


def pixel_rows(at_pixel: wp.array, n: int) -> tuple[wp.array, wp.array]:
    """(rank (npix + 1,) int32: the occupied pixels before each pixel, listed (n,) int32: the item at each
    occupied pixel in pixel order) of a pixel map whose pixels hold an item index (``at_pixel`` (npix,)
    int32; occupied where 0 <= index < n; an item at one pixel at most): the items of row y from x0 to
    x1 are listed[rank[y W + x0]] .. listed[rank[y W + x1 + 1] - 1], in x order. A window then reads its
    rows' items and skips their empty pixels (count, scan, write; nothing read to the host)."""
    check_array("at_pixel", at_pixel, None, wp.int32, "pixel_rows")
    dev = at_pixel.device
    npix = at_pixel.shape[0]
    if dev.is_cpu:
        # the host's memory is the device's: NumPy's vectorised count and scan, ~3x Warp's one-thread passes over
        # a full-size view's pixels (the same numbers)
        a = at_pixel.numpy()
        have = (a >= 0) & (a < n)
        rank = np.zeros(npix + 1, np.int32)
        np.cumsum(have, dtype=np.int32, out=rank[1:])
        listed = np.zeros(max(int(n), 1), np.int32)
        items = a[have]
        listed[:items.size] = items
        return (wp.array(rank, dtype=wp.int32, device=dev, copy=False),
                wp.array(listed, dtype=wp.int32, device=dev, copy=False))
    return _pixel_rows_launched(at_pixel, n)


def _pixel_rows_launched(at_pixel: wp.array, n: int) -> tuple[wp.array, wp.array]:
    """:func:`pixel_rows` by kernels (a GPU's way: count, scan, write on the device)."""
    dev = at_pixel.device
    npix = at_pixel.shape[0]
    flag = wp.zeros(npix + 1, dtype=wp.int32, device=dev)
    rank = wp.empty(npix + 1, dtype=wp.int32, device=dev)
    listed = wp.empty(max(int(n), 1), dtype=wp.int32, device=dev)
    if npix:
        wp.launch(occupied_kernel, dim=npix, inputs=[at_pixel, int(n)], outputs=[flag], device=dev)
    wp.utils.array_scan(flag, rank, inclusive=False)
    if npix:
        wp.launch(occupied_list_kernel, dim=npix, inputs=[at_pixel, int(n), rank], outputs=[listed], device=dev)
    return rank, listed


def gather(src: wp.array, index: wp.array, *, threads: int | None = None) -> wp.array:
    """src[index] ((m,), src's dtype: float32, float64, int32, vec2, vec3 or vec4) on src's device; ``index`` (m,)
    int32."""
    if not isinstance(src, wp.array) or src.ndim != 1 or src.dtype not in (wp.float32, wp.float64, wp.int32, wp.vec2,
                                                                            wp.vec3, wp.vec4):
        raise ValueError("gather: src must be a 1-D float32, float64, int32, vec2, vec3 or vec4 Warp array")
    m = check_array("index", index, None, wp.int32, "gather")
    out = wp.empty(m, dtype=src.dtype, device=src.device)
    launch_spans(gather_kernel, m, lambda i0: [src, index, i0], [out], src.device,
                 default_threads() if threads is None else threads)
    return out





def count_values(values: wp.array, bins: int, *, threads: int | None = None) -> np.ndarray:
    """(bins,) int64 how often each of 0 .. bins - 1 occurs in ``values`` ((n,) int32; others not
    counted): ``np.bincount(values, minlength=bins)[:bins]`` from a (ceil(n / SPAN), bins) read."""
    n = check_array("values", values, None, wp.int32, "count_values")
    rows = (n + SPAN - 1) // SPAN
    if rows == 0:
        return np.zeros(bins, np.int64)
    counts = wp.empty((rows, bins), dtype=wp.int32, device=values.device)
    launch_spans(count_values_kernel, rows, lambda i0: [values, int(bins), i0], [counts], values.device,
                 default_threads() if threads is None else threads, min_span=1)
    return counts.numpy().sum(axis=0, dtype=np.int64)


def set_at(a: wp.array, index: wp.array, value: int, *, threads: int | None = None) -> None:
    """a[index] = value on a's device (a (n,) int32, index (m,) int32)."""
    check_array("a", a, None, wp.int32, "set_at")
    m = check_array("index", index, None, wp.int32, "set_at")
    launch_spans(set_at_kernel, m, lambda i0: [index, int(value), i0], [a], a.device,
                 default_threads() if threads is None else threads)


def _host_order_stats(dev) -> bool:
    """Whether an order statistic of an array on ``dev`` is taken by NumPy on the array itself: on the CPU the
    array is host memory (no transfer), and NumPy's selection (``np.partition``: O(n)) beats a full radix sort
    (1.2M samples: a median 13 against 34 ms here). One name for the choice, so that the tests can run the
    device path on the CPU backend."""
    return dev.is_cpu


def _finite_host(a: wp.array) -> np.ndarray:
    """``a``'s finite values (a host array's own memory, read in place)."""
    x = a.numpy()
    return x[np.isfinite(x)]


def _sorted_finite(a: wp.array, fn: str) -> wp.array:
    """``a``'s ((n,) float32) finite values sorted ascending (a radix sort on a's device), with room for
    the sort's scratch (the first len(finite) are the values)."""
    check_array("a", a, None, wp.float32, fn)
    idx = finite_indices(a)
    m = idx.shape[0]
    if m == 0:
        return wp.empty(0, dtype=wp.float32, device=a.device)
    keys = wp.empty(2 * m, dtype=wp.float32, device=a.device)
    wp.copy(keys, gather(a, idx), count=m)
    values = wp.empty(2 * m, dtype=wp.int32, device=a.device)
    wp.utils.radix_sort_pairs(keys, values, m)
    return keys[:m]


def sort_finite(a: wp.array) -> wp.array:
    """``a``'s ((n,) float32) finite values sorted ascending, on a's device (a radix sort): for more
    than one order statistic of the same values (``median``, ``percentile32`` take it as ``a`` with
    ``presorted=True``)."""
    return _sorted_finite(a, "sort_finite")


def median(a: wp.array, *, dtype=np.float64, presorted: bool = False) -> float:
    """The median of ``a``'s ((n,) float32) finite values as ``np.median`` gives it for them in ``dtype``
    (float64: of their float64 copy; float32: of the values as they are; the mean of the two middle ones
    for an even count; NaN for none): two values read. ``presorted``: ``a`` is :func:`sort_finite`'s."""
    if not presorted:
        check_array("a", a, None, wp.float32, "median")
    if not presorted and _host_order_stats(a.device):
        fin = _finite_host(a)
        return float(np.median(fin.astype(dtype))) if fin.size else float("nan")
    s = a if presorted else _sorted_finite(a, "median")
    m = s.shape[0]
    if m == 0:
        return float("nan")
    mid = s[(m - 1) // 2:m // 2 + 1].numpy()
    return float(np.mean(mid.astype(dtype)))


def _lerp_sorted(s: wp.array, q: float, dtype) -> float:
    """NumPy's linear method at the fraction ``q`` (0..1) of the sorted values ``s`` (m >= 1): the virtual
    index (m - 1) q, its two neighbours read as ``dtype`` and their interpolation (from the upper one where
    the weight is >= 0.5), as ``np.percentile`` computes it."""
    m = s.shape[0]
    virtual = (m - 1) * float(q)
    lo = hi = m - 1
    if virtual < m - 1:
        lo = int(np.floor(virtual))
        hi = lo + 1
    a_lo, a_hi = (dtype(v) for v in s[lo:hi + 1].numpy()[[0, -1]])
    t = virtual - lo
    diff = a_hi - a_lo
    return float(a_hi - diff * (1 - t) if t >= 0.5 else a_lo + diff * t)


def percentiles(a: wp.array, q) -> tuple[list[float], int]:
    """(``np.percentile`` (its linear method) of ``a``'s ((n,) float32) finite values in float64 at each
    of ``q`` (percent; NaN for no value), how many values are finite): two values read a percentile."""
    check_array("a", a, None, wp.float32, "percentiles")
    qs = np.true_divide(np.asanyarray(q, np.float64), 100).ravel()
    if _host_order_stats(a.device):
        fin = _finite_host(a)
        if not fin.size:
            return [float("nan")] * qs.size, 0
        return [float(v) for v in np.percentile(fin.astype(np.float64), np.asanyarray(q, np.float64).ravel())], fin.size
    s = _sorted_finite(a, "percentiles")
    if s.shape[0] == 0:
        return [float("nan")] * qs.size, 0
    return [_lerp_sorted(s, qq, np.float64) for qq in qs], s.shape[0]


def percentile32(a: wp.array, q: float, *, presorted: bool = False) -> float:
    """``np.percentile`` of ``a``'s ((n,) float32) finite values at one scalar ``q`` (percent), as NumPy gives
    it for a float32 array and a scalar q: its linear method in float32 (NaN for no value). ``presorted``:
    ``a`` is :func:`sort_finite`'s."""
    if not presorted:
        check_array("a", a, None, wp.float32, "percentile32")
    if not presorted and _host_order_stats(a.device):
        fin = _finite_host(a)
        return float(np.percentile(fin, q)) if fin.size else float("nan")
    s = a if presorted else _sorted_finite(a, "percentile32")
    return _lerp_sorted(s, float(np.true_divide(q, 100)), np.float32) if s.shape[0] else float("nan")


def median64(a: wp.array) -> float:
    """``np.median`` of ``a`` ((n,) float64, n >= 1, every value >= 0 and finite): a radix sort of the
    values' bits as int64 keys (their order for non-negative floats) on a's device, two values read."""
    n = check_array("a", a, None, wp.float64, "median64")
    if n == 0:
        raise ValueError("median64: no values")
    if _host_order_stats(a.device):
        return float(np.median(a.numpy()))
    keys = wp.empty(2 * n, dtype=wp.float64, device=a.device)
    wp.copy(keys, a, count=n)
    bits = wp.array(ptr=keys.ptr, dtype=wp.int64, shape=(2 * n,), device=a.device)
    values = wp.empty(2 * n, dtype=wp.int32, device=a.device)
    wp.utils.radix_sort_pairs(bits, values, n)
    mid = keys[(n - 1) // 2:n // 2 + 1].numpy()
    return float(np.mean(mid))
