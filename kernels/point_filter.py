"""Point filtering by image-space neighbours (mixed pixels, isolated outliers).

A point triangulated from a pixel that straddles a depth edge (a mixed pixel) or
from a mis-sampled edge lands between surfaces, away from the points of the
pixels around it. This stage keeps a point only if enough of the points whose
pixels lie within ``radius`` pixels of its own are near it in 3D: within
``tolerance`` times the pixel footprint at its depth (mm per pixel = depth / f)
times their pixel distance, plus a floor. Points come in any order; each may
share its pixel with one other point (the +x and +y samples of a pixel).

Points in pixel order (the samplers write them so) are looked up where they lie:
a window row's points are a run of the arrays, entered through an index of the
first point of each block of BLOCK pixels (a pass over the points). Other orders
use a slot map of two entries a pixel (2 * H * W, filled with -1 first): the
same result, at the cost of writing and filling the map.
"""

from __future__ import annotations

from dataclasses import dataclass

import warp as wp

from ringscan.kernels.geometry import CameraModel
from ringscan.kernels.launch import default_threads, launch_spans

wp.set_module_options({"enable_backward": False})  # no gradients are taken here: no adjoint code to compile

MAX_PER_PIXEL = wp.constant(2)
FLOOR_FOOTPRINTS = wp.constant(0.5)
"""The filter's noise floor is at most this many pixel footprints (``NeighbourFilterSettings.floor_mm``)."""
BLOCK = wp.constant(16)
"""Pixels (raster order) per block of the sorted points' index (:func:`block_starts_kernel`)."""

__all__ = ["NeighbourFilterSettings", "mark_isolated_points"]


@dataclass(frozen=True)
class NeighbourFilterSettings:
    """Settings of the image-space neighbour filter."""

    radius: int = 2
    """Neighbourhood half-size in pixels (a (2r+1)^2 window); 0 disables the filter."""
    min_neighbours: int = 2
    """Points with fewer consistent neighbours are dropped."""
    tolerance: float = 3.0
    """A neighbour at pixel distance p is consistent if it lies within
    tolerance * p * footprint (+ floor) in 3D; 3 allows surfaces tilted up to
    ~70 degrees from the camera."""
    floor_mm: float = 0.05
    """Added to every distance threshold (noise floor, mm), at most ``FLOOR_FOOTPRINTS`` of the pixel's
    footprint: a scene whose units are not millimetres (a calibration in metres read as mm: footprints of
    a thousandth of a unit) keeps a filter that scales with it, where 0.05 would let every neighbour agree;
    on rigs in mm (footprints of 0.1 mm and more) the floor is 0.05 mm as it was."""


@wp.kernel
def map_pixels_kernel(pixel: wp.array(dtype=wp.int32), status: wp.array(dtype=wp.int32),
                      slots: wp.array(dtype=wp.int32)):
    """slots[2 * pixel[i] + k] = i, k = 0 for the first point of a pixel to arrive
    and 1 for the second (which is which does not change the filter's result).

    Only points with status 0 are mapped.
    pixel, status (n,) int32 read; slots (2 * H * W,) int32 written (pre-filled with -1).
    """
    i = wp.tid()
    if status[i] != 0:
        return
    p = pixel[i]
    old = wp.atomic_cas(slots, MAX_PER_PIXEL * p, -1, i)
    if old != -1:
        wp.atomic_cas(slots, MAX_PER_PIXEL * p + 1, -1, i)


@wp.func
def agrees(Y: wp.vec3, X: wp.vec3, dx: int, dy: int, foot: float, tolerance: float, floor_mm: float):
    """Whether neighbour Y, (dx, dy) pixels from point X, lies within the filter's
    distance of it: ``tolerance`` pixel footprints ``foot`` (mm) a pixel of
    separation (at least one) plus ``floor_mm``."""
    pd = wp.sqrt(float(dx * dx + dy * dy))
    return wp.length(Y - X) <= tolerance * wp.max(pd, 1.0) * foot + wp.min(floor_mm, FLOOR_FOOTPRINTS * foot)


@wp.kernel
def count_neighbours_kernel(
    points: wp.array(dtype=wp.vec3),
    pixel: wp.array(dtype=wp.int32),
    status: wp.array(dtype=wp.int32),
    slots: wp.array(dtype=wp.int32),
    cam: CameraModel,
    width: int,
    height: int,
    radius: int,
    tolerance: float,
    floor_mm: float,
    min_neighbours: int,
    isolated_status: int,
    i0: int,
    status_out: wp.array(dtype=wp.int32),
):
    """status_out[i] = isolated_status where point i = i0 + tid (status 0) has
    fewer than min_neighbours consistent image neighbours, else status[i]. The
    window is walked row by row and left as soon as enough neighbours agree.

    points (n,) vec3 world, pixel/status (n,) int32, slots (2 * H * W,) int32: read.
    status_out (n,) int32: written.

    Size: Warp kernels take each array and the camera as its own argument, plus the image size and the filter's
    scalar settings (radius, tolerance, floor_mm, min_neighbours, the status to give).
    """
    i = i0 + wp.tid()
    status_out[i] = status[i]
    if status[i] != 0:
        return
    X = points[i]
    p = pixel[i]
    y = p / width
    x = p - y * width
    depth = wp.length(X - cam.center)
    foot = depth / cam.fx
    n = int(0)
    win = 2 * radius + 1
    for q in range(win * win):
        if n >= min_neighbours:
            break
        dy = q / win - radius
        dx = q - (q / win) * win - radius
        yy = y + dy
        xx = x + dx
        if yy >= 0 and yy < height and xx >= 0 and xx < width:
            for k in range(MAX_PER_PIXEL):
                j = slots[MAX_PER_PIXEL * (yy * width + xx) + k]
                if j >= 0 and j != i:
                    if agrees(points[j], X, dx, dy, foot, tolerance, floor_mm):
                        n = n + 1
    if n < min_neighbours:
        status_out[i] = isolated_status


@wp.kernel
def unsorted_kernel(pixel: wp.array(dtype=wp.int32), flag: wp.array(dtype=wp.int32)):
    """flag[0] = 1 where pixel[i] > pixel[i + 1]. pixel (n,) read; flag (1,) written (pre-filled with 0)."""
    i = wp.tid()
    if pixel[i] > pixel[i + 1]:
        flag[0] = 1


@wp.func
def pixel_block(p: int, n_blocks: int):
    """Block of pixel index p (BLOCK consecutive pixels of the raster), clamped to
    -1..n_blocks (a pixel outside the image only ever meets its own blocks)."""
    return wp.where(p < 0, -1, wp.min(p / BLOCK, n_blocks))


@wp.kernel
def block_starts_kernel(pixel: wp.array(dtype=wp.int32), n_blocks: int, starts: wp.array(dtype=wp.int32)):
    """starts[b] = the first point whose pixel is in block b or after it (pixel
    sorted): point i writes the blocks after its predecessor's up to its own,
    thread n those after the last point's.

    pixel (n,) read; starts (n_blocks + 1,) written, each entry by one thread.
    """
    i = wp.tid()
    prev = int(-1)
    if i > 0:
        prev = pixel_block(pixel[i - 1], n_blocks)
    cur = n_blocks
    if i < pixel.shape[0]:
        cur = pixel_block(pixel[i], n_blocks)
    for bb in range(prev + 1, cur + 1):
        starts[bb] = i


@wp.kernel
def count_neighbours_sorted_kernel(
    points: wp.array(dtype=wp.vec3),
    pixel: wp.array(dtype=wp.int32),
    status: wp.array(dtype=wp.int32),
    starts: wp.array(dtype=wp.int32),
    cam: CameraModel,
    width: int,
    height: int,
    radius: int,
    tolerance: float,
    floor_mm: float,
    min_neighbours: int,
    isolated_status: int,
    i0: int,
    status_out: wp.array(dtype=wp.int32),
):
    """:func:`count_neighbours_kernel` for points sorted by pixel: a window row's
    points are a run of the arrays, entered at the first point of the block of
    BLOCK pixels that holds the row's first column, so no slot map is needed. Same
    result: every status-0 point of the window counts.

    points (n,) vec3 world, pixel/status (n,) int32, starts (n_blocks + 1,) int32
    (:func:`block_starts_kernel`): read. status_out (n,) int32: written.

    Size: the same arguments as count_neighbours_kernel, with the block starts in place of the slot map, so the
    two launch alike.
    """
    i = i0 + wp.tid()
    status_out[i] = status[i]
    if status[i] != 0:
        return
    X = points[i]
    p = pixel[i]
    y = p / width
    x = p - y * width
    depth = wp.length(X - cam.center)
    foot = depth / cam.fx
    n = int(0)
    xa = wp.max(x - radius, 0)
    xb = wp.min(x + radius, width - 1)
    n_all = pixel.shape[0]
    for dy in range(-radius, radius + 1):
        yy = y + dy
        if n < min_neighbours and yy >= 0 and yy < height:
            row = yy * width
            hi = n_all
            j = starts[(row + xa) / BLOCK]
            while j < hi and pixel[j] < row + xa:
                j = j + 1
            while j < hi and n < min_neighbours:
                q = pixel[j]
                if q > row + xb:
                    j = hi
                else:
                    if status[j] == 0 and j != i:
                        if agrees(points[j], X, q - row - x, dy, foot, tolerance, floor_mm):
                            n = n + 1
                    j = j + 1
    if n < min_neighbours:
        status_out[i] = isolated_status


def mark_isolated_points(
    points: wp.array,
    pixel: wp.array,
    status: wp.array,
    *,
    camera: CameraModel,
    width: int,
    height: int,
    isolated_status: int,
    settings: NeighbourFilterSettings = NeighbourFilterSettings(),
    threads: int | None = None,
) -> wp.array:
    """New status array in which the points (status 0) that disagree with their
    image neighbours get ``isolated_status``.

    Args:
        points: (n,) vec3 world points.
        pixel: (n,) int32 linear pixel index y * width + x of each point (at most
            two points per pixel).
        status: (n,) int32; only status-0 points take part.
        camera: the camera that saw them (centre and focal length give the
            pixel footprint).
        width, height: image size.
        isolated_status: the status code given to dropped points.
        settings: filter settings.
        threads: CPU threads (spans of points); default: all cores.

    Size: a public function: the point arrays and its documented keyword-only options (camera, image size, the
    status to give, settings, threads).
    """
    if not isinstance(points, wp.array) or points.dtype != wp.vec3:
        raise ValueError("mark_isolated_points: points must be a Warp array of vec3")
    n = points.shape[0]
    for name, a in (("pixel", pixel), ("status", status)):
        if not isinstance(a, wp.array) or a.dtype != wp.int32 or a.shape != (n,):
            raise ValueError(f"mark_isolated_points: {name} must be a ({n},) int32 Warp array")
    dev = points.device
    if n == 0 or settings.radius <= 0:
        return wp.clone(status)
    out = wp.empty_like(status)
    threads = default_threads() if threads is None else threads
    args = [points, pixel, status]
    tail = [camera, width, height, settings.radius, settings.tolerance, settings.floor_mm, settings.min_neighbours,
            isolated_status]
    unsorted = wp.zeros(1, dtype=wp.int32, device=dev)
    if n > 1:
        wp.launch(unsorted_kernel, dim=n - 1, inputs=[pixel], outputs=[unsorted], device=dev)
    if not unsorted.numpy()[0]:
        # points in pixel order (the samplers write them so): each window row's points
        # are a run of the arrays, found from the first point of each block of BLOCK pixels
        n_blocks = (width * height + BLOCK - 1) // BLOCK
        starts = wp.empty(n_blocks + 1, dtype=wp.int32, device=dev)
        wp.launch(block_starts_kernel, dim=n + 1, inputs=[pixel, n_blocks], outputs=[starts], device=dev)
        launch_spans(count_neighbours_sorted_kernel, n, lambda i0: args + [starts] + tail + [i0], [out], dev, threads)
        return out
    slots = wp.full(MAX_PER_PIXEL * width * height, -1, dtype=wp.int32, device=dev)
    wp.launch(map_pixels_kernel, dim=n, inputs=[pixel, status], outputs=[slots], device=dev)
    launch_spans(count_neighbours_kernel, n, lambda i0: args + [slots] + tail + [i0], [out], dev, threads)
    return out
