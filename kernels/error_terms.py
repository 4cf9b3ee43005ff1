"""The error model's per-sample work on the samples' device (docs/reconstruction.md, "Honest
sigma"): ``pipeline.reconstruct.error_scale`` fits the model on the host from a bounded subset of
the samples (at most ``MAX_CHECK_SAMPLES``, gathered by ``kernels.compact``); what touches every
sample stays here: the fitted terms applied to every sample (``widen_sigmas``: the same values to
the bit as ``error_scale.apply_error_model`` and ``region_scale`` in NumPy)."""

from __future__ import annotations

import numpy as np
import warp as wp

from ringscan.kernels.launch import check_array, default_threads, launch_spans

wp.set_module_options({"enable_backward": False})  # no gradients are taken here: no adjoint code to compile

__all__ = ["ErrorTerms", "widen_sigmas"]


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
    uv: wp.array(dtype=wp.vec2),
    grid: wp.array2d(dtype=wp.float64),
    terms: ErrorTerms,
    i0: int,
    out: wp.array(dtype=wp.float32),
):
    """out[i] = float32(sqrt(k^2 s^2 + floor^2 + (indirect_px max(b - median, 0))^2)), times the square
    root of the factor of the tile under uv[i] where ``grid`` has tiles (rounded to float32 after).

    sigma (n,) float32 the decode's s (projector px); indirect (n,) float32 each sample's share b
    (read only with indirect_px > 0); uv (n,) vec2 (read only with a grid of tiles); grid (rows,
    cols) float64 the tiles' variance factors (1 where none; (0, 0): no tiles): read. out (n,)
    float32: written.

    Size: the three per-sample arrays, the tiles' grid, the terms, the span's i0, one array out."""
    i = i0 + wp.tid()
    ks = terms.k * wp.float64(sigma[i])
    var = ks * ks + terms.floor2
    if terms.indirect_px > wp.float64(0.0):
        b = terms.indirect_px * wp.max(wp.float64(indirect[i]) - terms.indirect_median, wp.float64(0.0))
        var = var + b * b
    w = wp.float32(wp.sqrt(var))
    if grid.shape[0] > 0:
        tx = int(wp.floor(wp.float64(uv[i][0]) / terms.tile_px)) - terms.tx0
        ty = int(wp.floor(wp.float64(uv[i][1]) / terms.tile_px)) - terms.ty0
        f = wp.float64(1.0)
        if tx >= 0 and tx < grid.shape[1] and ty >= 0 and ty < grid.shape[0]:
            f = grid[ty, tx]
        w = wp.float32(wp.float64(w) * wp.sqrt(f))
    out[i] = w


# ----------------------------------------------------------------------------- host


def widen_sigmas(sigma: wp.array, *, k: float, floor: float, indirect: wp.array | None = None,
                 indirect_px: float = 0.0, indirect_median: float = 0.0, uv: wp.array | None = None,
                 regions: dict | None = None, threads: int | None = None) -> wp.array:
    """(n,) float32 sigmas widened by one coordinate's fitted terms (:func:`widen_kernel`), on sigma's
    device: ``error_scale.apply_error_model`` (k, floor, the indirect share above ``indirect_median``
    at ``indirect_px`` a unit) times the square root of ``regions``' tile factor
    (``error_scale.region_scale``: {"tile_px", "scales": [[tx, ty, factor], ...]}) under ``uv``.

    Size: the sigmas, the model's four terms for this coordinate (k, floor, indirect px and median),
    the two per-sample arrays they read (indirect, uv), the tiles, the thread count."""
    fn = "widen_sigmas"
    n = check_array("sigma", sigma, None, wp.float32, fn)
    dev = sigma.device
    use_indirect = indirect_px > 0 and indirect is not None
    if use_indirect:
        check_array("indirect", indirect, n, wp.float32, fn)
    table = np.asarray(regions["scales"], np.float64).reshape(-1, 3) if regions and regions.get("scales") else None
    terms = ErrorTerms()
    terms.k = float(k)
    terms.floor2 = float(floor) ** 2
    terms.indirect_px = float(indirect_px) if use_indirect else 0.0
    terms.indirect_median = float(indirect_median)
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
    args = [sigma, indirect if use_indirect else sigma, uv if table is not None else wp.empty(0, dtype=wp.vec2, device=dev),
            grid, terms]
    launch_spans(widen_kernel, n, lambda i0: args + [i0], [out], dev, default_threads() if threads is None else threads)
    return out
