"""The samples of an imported scan's decoded maps (the ``decoded`` codec's stage): one sample per pixel
whose projector column and row were decoded on import, with its polar coordinates about the pattern centre
and its predicted errors, on the frames' device (count, scan, write)."""

from __future__ import annotations

import warp as wp

from ringscan.kernels.launch import default_threads, launch_rows, row_run, scan_counts
from ringscan.kernels.light_gradient import shading_at
from ringscan.kernels.samples import Samples

wp.set_module_options({"enable_backward": False})  # no gradients are taken here: no adjoint code to compile

__all__ = ["DecodedMapParams", "decoded_map_samples"]


@wp.struct
class DecodedMapParams:
    """How :func:`decoded_map_samples` reads a decoded map (the ``decoded`` codec's constants)."""

    scale: wp.float64
    """Fixed-point steps per projector px: coordinate = value / scale - 1 (value 0: not decoded)."""
    contrast_scale: wp.float64
    """Contrast frame units per 8-bit level (257: a 16-bit frame)."""
    center: wp.vec2d
    """The pattern centre (projector px): rho and phi are taken about it."""
    sectors: wp.int32
    """2 ** sector_bits, or 0: no sector (-1)."""
    contrast_full: wp.float64
    """Contrast (8-bit levels) at which the confidence reaches 1."""
    sigma_subpixel: wp.float64
    """Sigma (projector px) of a sub-pixel coordinate at ``contrast_full`` (as 1 / contrast)."""
    sigma_integer: wp.float64
    """Sigma of an integer coordinate (1 / sqrt 12)."""
    light_gradient: wp.int32
    """1: each sample's ``shading`` (the light's gradient) is computed; 0: not (camera 2 of a two-camera
    view: matching reads none), and ``shading`` is not written."""


@wp.func
def is_integer_code(x: wp.float64, prm: DecodedMapParams):
    """Whether decoded coordinate x is an integer code (a whole pixel: the import writes sub-pixel ones off it)."""
    return wp.abs(x - wp.round(x)) < wp.float64(0.5) / prm.scale


@wp.func
def decoded_sigma(x: wp.float64, con: wp.float64, prm: DecodedMapParams):
    """Predicted sigma (projector px) of decoded coordinate x at contrast con: an integer code's, or a
    sub-pixel one's (as 1 / contrast, floored at the fixed point's step)."""
    if is_integer_code(x, prm):
        return prm.sigma_integer
    floor = wp.float64(1.0) / (prm.scale * wp.sqrt(wp.float64(12.0)))
    return wp.max(prm.sigma_subpixel * prm.contrast_full / wp.max(con, wp.float64(1.0)), floor)


@wp.func
def coordinate_at(f: wp.array2d(dtype=wp.uint16), y: int, x: int, prm: DecodedMapParams):
    """The map's projector coordinate at (y, x) (float64), and whether it was decoded (False outside)."""
    if y < 0 or x < 0 or y >= f.shape[0] or x >= f.shape[1]:
        return wp.float64(0.0), False
    a = f[y, x]
    return wp.float64(a) / prm.scale - wp.float64(1.0), a > wp.uint16(0)


@wp.func
def axis_step(f: wp.array2d(dtype=wp.uint16), y: int, x: int, dy: int, dx: int, c: wp.float64,
              prm: DecodedMapParams):
    """|change| of the map's coordinate (projector px) to the next decoded pixel along (dy, dx), the smaller
    of the two sides (a depth edge on one side is not the map's slope); 0 with neither decoded."""
    a, ok_a = coordinate_at(f, y + dy, x + dx, prm)
    b, ok_b = coordinate_at(f, y - dy, x - dx, prm)
    da = wp.abs(a - c)
    db = wp.abs(c - b)
    if ok_a and ok_b:
        return wp.min(da, db)
    if ok_a:
        return da
    if ok_b:
        return db
    return wp.float64(0.0)


@wp.func
def map_rate(f: wp.array2d(dtype=wp.uint16), y: int, x: int, c: wp.float64, prm: DecodedMapParams):
    """Projector px per camera px of the map at (y, x) (the norm of its smaller one-sided steps across and
    down): a sub-pixel position's error is the crossing's in the camera times this where above 1 (a camera
    coarser than the projector; ``graycode.resolution_levels``)."""
    gx = axis_step(f, y, x, 0, 1, c, prm)
    gy = axis_step(f, y, x, 1, 0, c, prm)
    return wp.sqrt(gx * gx + gy * gy)


@wp.kernel
def decoded_flags_kernel(
    fu: wp.array2d(dtype=wp.uint16),
    fv: wp.array2d(dtype=wp.uint16),
    row0: int,
    chunk: int,
    flags: wp.array(dtype=wp.int32),
):
    """flags[y * W + x] = 1 where both coordinates were decoded, ``chunk`` pixels of one row per thread.
    fu, fv (H, W) uint16: read; flags (H * W,) int32: written."""
    w = fu.shape[1]
    run = row_run(wp.tid(), w, row0, chunk)
    y = run[0]
    for x in range(run[1], run[2]):
        flags[y * w + x] = wp.where(fu[y, x] > wp.uint16(0) and fv[y, x] > wp.uint16(0), 1, 0)


@wp.kernel
def decoded_samples_kernel(
    fu: wp.array2d(dtype=wp.uint16),
    fv: wp.array2d(dtype=wp.uint16),
    fc: wp.array2d(dtype=wp.uint16),
    offsets: wp.array(dtype=wp.int32),
    prm: DecodedMapParams,
    row0: int,
    chunk: int,
    uv: wp.array(dtype=wp.vec2),
    rho: wp.array(dtype=wp.float32),
    phi: wp.array(dtype=wp.float32),
    sector: wp.array(dtype=wp.int32),
    confidence: wp.array(dtype=wp.float32),
    pixel: wp.array(dtype=wp.int32),
    sigma_rho: wp.array(dtype=wp.float32),
    sigma_tan: wp.array(dtype=wp.float32),
    shading: wp.array(dtype=wp.float32),
):
    """Each decoded pixel's sample at its scanned offset, ``chunk`` pixels of one row per thread: the polar
    coordinates about the centre and the u and v sigmas turned radial and tangential (float64, then float32),
    and the light's gradient there (``kernels.light_gradient.shading_at`` on the contrast frame).

    fu, fv, fc (H, W) uint16 (proj_u, proj_v, contrast), offsets (H * W,) int32 (the flags' exclusive scan):
    read. uv (n,) vec2, rho, phi, confidence, sigma_rho, sigma_tan, shading (n,) float32 (shading: with
    ``prm.light_gradient``; else unread, any size), sector, pixel (n,) int32: written.

    Size: Warp kernels take each array as its own argument: the three frames and the offsets in, the nine
    fields of :class:`Samples` out; the codec's constants travel in DecodedMapParams.
    """
    w = fu.shape[1]
    run = row_run(wp.tid(), w, row0, chunk)
    y = run[0]
    for x in range(run[1], run[2]):
        a = fu[y, x]
        b = fv[y, x]
        if a > wp.uint16(0) and b > wp.uint16(0):
            i = y * w + x
            o = offsets[i]
            up = wp.float64(a) / prm.scale - wp.float64(1.0)
            vp = wp.float64(b) / prm.scale - wp.float64(1.0)
            du = up - prm.center[0]
            dv = vp - prm.center[1]
            f = wp.atan2(dv, du)
            con = wp.float64(fc[y, x]) / prm.contrast_scale
            su = decoded_sigma(up, con, prm)
            sv = decoded_sigma(vp, con, prm)
            # a sub-pixel coordinate's sigma is the crossing's, in the camera: where a camera px spans more
            # than one projector px, that many times more (an integer code's is its own)
            if not is_integer_code(up, prm):
                su = su * wp.max(map_rate(fu, y, x, up, prm), wp.float64(1.0))
            if not is_integer_code(vp, prm):
                sv = sv * wp.max(map_rate(fv, y, x, vp, prm), wp.float64(1.0))
            c = wp.cos(f)
            s = wp.sin(f)
            c2 = c * c
            s2 = s * s
            uv[o] = wp.vec2(float(x), float(y))
            rho[o] = wp.float32(wp.sqrt(du * du + dv * dv))
            phi[o] = wp.float32(f)
            sec = int(-1)
            if prm.sectors > 0:
                k = wp.floor((f + wp.float64(wp.pi)) / (wp.float64(2.0) * wp.float64(wp.pi))
                             * wp.float64(prm.sectors))
                sec = wp.clamp(int(k), 0, prm.sectors - 1)
            sector[o] = sec
            confidence[o] = wp.float32(wp.clamp(con / prm.contrast_full, wp.float64(0.0), wp.float64(1.0)))
            pixel[o] = i
            sigma_rho[o] = wp.float32(wp.sqrt(su * su * c2 + sv * sv * s2))
            sigma_tan[o] = wp.float32(wp.sqrt(su * su * s2 + sv * sv * c2))
            if prm.light_gradient != 0:
                shading[o] = wp.float32(shading_at(fc, uv[o], prm.contrast_scale))


def decoded_map_samples(frames: wp.array, *, params: DecodedMapParams, threads: int | None = None) -> Samples:
    """One sample per decoded pixel of an imported scan's maps, in raster order (count, scan, write on the
    frames' device).

    Args:
        frames: (3, H, W) uint16 Warp array: proj_u, proj_v (fixed point, 0: not decoded), contrast.
        params: :class:`DecodedMapParams`.
        threads: CPU threads (row slices); default: all cores.

    Returns:
        :class:`Samples` with ``uv`` the pixel, ``rho``/``phi`` about the centre, ``sector`` (-1 without
        sectors), ``confidence``, ``pixel``, ``sigma_rho``/``sigma_tan``, ``shading`` (None where
        ``params.light_gradient`` is 0); ``ring`` None.
    """
    if not isinstance(frames, wp.array) or frames.dtype != wp.uint16 or frames.ndim != 3 or frames.shape[0] != 3:
        raise ValueError("decoded_map_samples: frames must be a (3, H, W) uint16 Warp array")
    _, h, w = frames.shape
    dev = frames.device
    fu, fv, fc = frames[0], frames[1], frames[2]
    threads = default_threads() if threads is None else threads
    total = 0
    if h * w:
        flags = wp.empty(h * w, dtype=wp.int32, device=dev)
        launch_rows(decoded_flags_kernel, h, w, lambda r0, chunk: [fu, fv, r0, chunk], [flags], dev, threads)
        offsets, total = scan_counts(flags)
    f32 = lambda: wp.empty(total, dtype=wp.float32, device=dev)  # noqa: E731
    out = Samples(uv=wp.empty(total, dtype=wp.vec2, device=dev), rho=f32(), ring=None,
                  sector=wp.empty(total, dtype=wp.int32, device=dev), confidence=f32(),
                  pixel=wp.empty(total, dtype=wp.int32, device=dev), phi=f32(), sigma_rho=f32(), sigma_tan=f32(),
                  shading=f32() if params.light_gradient else None)
    if total:
        shading = out.shading if out.shading is not None else wp.empty(0, dtype=wp.float32, device=dev)
        launch_rows(decoded_samples_kernel, h, w, lambda r0, chunk: [fu, fv, fc, offsets, params, r0, chunk],
                    [out.uv, out.rho, out.phi, out.sector, out.confidence, out.pixel, out.sigma_rho, out.sigma_tan,
                     shading],
                    dev, threads)
    return out
