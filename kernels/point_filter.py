"""Point filtering by image-space neighbours (mixed pixels, isolated outliers).

A point triangulated from a pixel that straddles a depth edge (a mixed pixel) or
from a mis-sampled edge lands between surfaces, away from the points of the
pixels around it. This stage keeps a point only if enough of the points whose
pixels lie within ``radius`` pixels of its own are near it in 3D: within
``tolerance`` times the pixel footprint at its depth (mm per pixel = depth / f)
times their pixel distance, plus a floor. Points come in any order; each may
share its pixel with one other point (the +x and +y samples of a pixel).
"""

from __future__ import annotations

from dataclasses import dataclass

import warp as wp

from ringscan.kernels.geometry import CameraModel
from ringscan.kernels.launch import default_threads, launch_spans

MAX_PER_PIXEL = wp.constant(2)

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
    """Added to every distance threshold (noise floor, mm)."""


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
            pd = wp.sqrt(float(dx * dx + dy * dy))
            lim = tolerance * wp.max(pd, 1.0) * foot + floor_mm
            for k in range(MAX_PER_PIXEL):
                j = slots[MAX_PER_PIXEL * (yy * width + xx) + k]
                if j >= 0 and j != i:
                    if wp.length(points[j] - X) <= lim:
                        n = n + 1
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
    slots = wp.full(MAX_PER_PIXEL * width * height, -1, dtype=wp.int32, device=dev)
    out = wp.empty_like(status)
    wp.launch(map_pixels_kernel, dim=n, inputs=[pixel, status], outputs=[slots], device=dev)
    args = [points, pixel, status, slots, camera, width, height, settings.radius, settings.tolerance,
            settings.floor_mm, settings.min_neighbours, isolated_status]
    launch_spans(count_neighbours_kernel, n, lambda i0: args + [i0], [out], dev,
                 default_threads() if threads is None else threads)
    return out
