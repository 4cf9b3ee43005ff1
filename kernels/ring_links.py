"""Single-shot ``rings`` codec, per sample: ring roots and gap links (docs/design.md §3, §10).

Ring roots (:func:`ring_roots`): for sample i and candidate radius rho_k the
camera ray meets the ring's quadric (cylinder for a parallel light, cone for a
perspective one, Newton steps for projector distortion) at up to two points,
through the same :func:`ringscan.kernels.ring_quadric.ray_ring_roots` that
triangulation uses; each is kept when it lies in front of the camera and inside
the working volume. The labelling stage (``pipeline.codecs.single_shot``) tests
its hypotheses with them.

Gap links (:func:`link_lines`): from every line centre a march across the line,
both ways, finds the first centre of another curve, and checks that the gap
between them is one clean valley of the smoothed image (no faint line inside it).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import warp as wp

from ringscan.kernels.geometry import (
    CameraModel,
    LightModel,
    Volume,
    camera_ray,
    make_volume,
)
from ringscan.kernels.ring_lines import bilinear
from ringscan.kernels.ring_quadric import pattern_offset, ray_ring_roots, root_usable

wp.set_module_options({"enable_backward": False})  # no gradients are taken here: no adjoint code to compile

__all__ = ["RingRoots", "ring_roots", "link_lines"]


@dataclass
class RingRoots:
    """Where each sample's camera ray meets each candidate ring (Warp arrays)."""

    points: wp.array
    """(n, k, 2) vec3 world points of the two roots (nearer first); zero where invalid."""
    offset: wp.array
    """(n, k, 2) vec2 projector offset p - c of each root (its polar angle on the
    pattern); zero where invalid."""
    valid: wp.array
    """(n, k) int32 bit mask: bit 0 = root 0 usable, bit 1 = root 1 usable (in
    front of the camera, inside the working volume, in front of a perspective
    light, and, with projector distortion, its refinement converged). 0 where
    the camera pixel has no undistorted ray (``geometry.undistort``)."""


@wp.kernel
def ring_roots_kernel(
    uv: wp.array(dtype=wp.vec2),
    radii: wp.array(dtype=wp.float32),
    cam: CameraModel,
    light: LightModel,
    vol: Volume,
    center: wp.vec2,
    points: wp.array3d(dtype=wp.vec3),
    offset: wp.array3d(dtype=wp.vec2),
    valid: wp.array2d(dtype=wp.int32),
):
    """Both meetings of sample i's camera ray with ring k's quadric (thread (i, k)).

    uv (n,) vec2 camera px and radii (k,) float32 projector px: read.
    points (n, k, 2) vec3, offset (n, k, 2) vec2, valid (n, k) int32: written.

    Size: Warp kernels take each array, the camera, the light and the volume as its own argument.
    """
    i, k = wp.tid()
    d, ray_ok = camera_ray(cam, uv[i][0], uv[i][1])
    C = cam.center
    zero3 = wp.vec3(0.0, 0.0, 0.0)
    zero2 = wp.vec2(0.0, 0.0)
    points[i, k, 0] = zero3
    points[i, k, 1] = zero3
    offset[i, k, 0] = zero2
    offset[i, k, 1] = zero2
    valid[i, k] = 0
    if not ray_ok:
        return
    roots, failed = ray_ring_roots(light, C, d, radii[k], center)
    if roots[2] == 0.0:
        return
    mask = int(0)
    for m in range(2):
        t = roots[m]
        X = C + d * t
        if (failed & (1 << m)) == 0 and root_usable(light, X, t, vol):
            points[i, k, m] = X
            offset[i, k, m] = pattern_offset(light, X, center)
            mask = mask | (1 << m)
    valid[i, k] = mask


@wp.kernel
def link_lines_kernel(
    uv: wp.array(dtype=wp.vec2),
    normal: wp.array(dtype=wp.vec2),
    piece: wp.array(dtype=wp.int32),
    sample_map: wp.array2d(dtype=wp.int32),
    image: wp.array2d(dtype=wp.float32),
    max_gap: float,
    step: float,
    self_gap: float,
    bump_contrast: float,
    neighbour: wp.array2d(dtype=wp.int32),
    gap: wp.array2d(dtype=wp.float32),
    bump: wp.array2d(dtype=wp.int32),
):
    """March from sample i across its line, along +normal (side 0) and -normal
    (side 1), to the first line centre met within ``max_gap`` px, and check that
    the gap between them is one clean valley of the (smoothed) image.

    A centre of another piece ends the march at once; one of the sample's own
    piece only beyond ``self_gap`` px (the far side of a closed curve). Pieces
    < 0 are ignored. The gap holds a bump when, after the profile has risen
    ``bump_contrast`` grey levels above its lowest point, it falls again by as
    much before the centre met: a faint line (a ring too weak or too crowded to be
    detected) lies between.

    uv, normal (n,) vec2, piece (n,) int32, sample_map (H, W) int32 (sample index
    per pixel, -1 for none), image (H, W) float32: read.
    neighbour (n, 2) int32 (sample met, -1 for none), gap (n, 2) float32 (its
    distance along the normal, px), bump (n, 2) int32 (1: the gap holds a bump):
    written.

    Size: one thread per sample: both sides' marches share the sample's position and normal, and each march's
    valley check reads the profile it walks. Warp kernels take each array as its own argument, plus the march's
    four scalar settings.
    """
    i = wp.tid()
    h = sample_map.shape[0]
    w = sample_map.shape[1]
    p = uv[i]
    own = piece[i]
    for side in range(2):
        sg = wp.where(side == 0, 1.0, -1.0)
        n = normal[i] * sg
        tx = -n[1]
        ty = n[0]
        found = int(-1)
        dist = float(0.0)
        s = step
        while s <= max_gap and found < 0 and own >= 0:
            qx = p[0] + n[0] * s
            qy = p[1] + n[1] * s
            x0 = int(wp.floor(qx))
            y0 = int(wp.floor(qy))
            best = float(1.0e9)
            for k in range(4):
                xx = x0 + (k % 2)
                yy = y0 + (k / 2)
                if xx >= 0 and yy >= 0 and xx < w and yy < h:
                    j = sample_map[yy, xx]
                    if j >= 0 and j != i and piece[j] >= 0:
                        dq = uv[j] - p
                        along = dq[0] * n[0] + dq[1] * n[1]
                        across = wp.abs(dq[0] * tx + dq[1] * ty)
                        other = piece[j] != own
                        if along > 0.0 and (other or along > self_gap) and across < best:
                            best = across
                            found = j
                            dist = along
            s = s + step
        neighbour[i, side] = found
        gap[i, side] = dist
        bumped = int(0)
        if found >= 0:
            # one valley between the two centres: no rise-then-fall on the way
            lo = bilinear(image, p[0], p[1])
            hi = lo
            rising = int(0)
            s = step
            while s < dist and bumped == 0:
                v = bilinear(image, p[0] + n[0] * s, p[1] + n[1] * s)
                if rising == 0:
                    lo = wp.min(lo, v)
                    if v >= lo + bump_contrast:
                        rising = 1
                        hi = v
                else:
                    hi = wp.max(hi, v)
                    if v <= hi - bump_contrast:
                        bumped = 1
                s = s + step
        bump[i, side] = bumped


@wp.kernel
def scatter_samples_kernel(pixel: wp.array(dtype=wp.int32), sample_map: wp.array(dtype=wp.int32)):
    """sample_map[pixel[i]] = i. pixel (n,) int32 read; sample_map (H * W,) int32 written."""
    i = wp.tid()
    sample_map[pixel[i]] = i


def ring_roots(
    uv: wp.array,
    radii,
    *,
    camera: CameraModel,
    light: LightModel,
    volume: tuple[float, float, float],
    center: tuple[float, float],
) -> RingRoots:
    """Both meetings of every sample's camera ray with every candidate ring.

    Args:
        uv: (n,) vec2 camera pixel coordinates (distorted image).
        radii: (k,) ring radii in projector px (sequence or float32 Warp array).
        camera, light: from :mod:`ringscan.kernels.geometry`.
        volume: (z_min, z_max, r_max) of the working volume (world mm).
        center: pattern centre (c_u, c_v) in projector px.

    Returns:
        :class:`RingRoots` on uv's device.
    """
    if not isinstance(uv, wp.array) or uv.dtype != wp.vec2 or uv.ndim != 1:
        raise ValueError("ring_roots: uv must be a 1D Warp array of vec2")
    dev = uv.device
    if isinstance(radii, wp.array):
        if radii.dtype != wp.float32 or radii.ndim != 1:
            raise ValueError("ring_roots: radii must be a 1D float32 array")
        rad = radii if radii.device == dev else wp.clone(radii, device=dev)
    else:
        r = np.asarray(radii, np.float32).ravel()
        if not np.all(np.isfinite(r)) or np.any(r < 0):
            raise ValueError("ring_roots: radii must be finite and >= 0")
        rad = wp.array(r, dtype=wp.float32, device=dev)
    z_min, z_max, r_max = (float(x) for x in volume)
    if not (z_max > z_min and r_max > 0):
        raise ValueError(f"ring_roots: bad volume {volume}")
    n, k = uv.shape[0], rad.shape[0]
    out = RingRoots(points=wp.zeros((n, k, 2), dtype=wp.vec3, device=dev),
                    offset=wp.zeros((n, k, 2), dtype=wp.vec2, device=dev),
                    valid=wp.zeros((n, k), dtype=wp.int32, device=dev))
    if n * k:
        wp.launch(ring_roots_kernel, dim=(n, k),
                  inputs=[uv, rad, camera, light, make_volume(z_min, z_max, r_max), wp.vec2(*center)],
                  outputs=[out.points, out.offset, out.valid], device=dev)
    return out


def link_lines(
    uv: wp.array,
    normal: wp.array,
    piece: wp.array,
    *,
    image: wp.array,
    pixel: wp.array,
    max_gap: float,
    self_gap: float = 3.0,
    bump_contrast: float = 2.0,
    step: float = 0.35,
) -> tuple[wp.array, wp.array, wp.array]:
    """For every line sample, the nearest line sample across it on each side, and
    whether the gap between them holds a bump (a faint line).

    Args:
        uv, normal: (n,) vec2 sample centres and normals (oriented as the caller
            wants its sides: side 0 is +normal).
        piece: (n,) int32 curve id of each sample (-1: ignore the sample).
        image: (H, W) float32 smoothed frame (:func:`smooth_frame`, or
            ``RingLines.smoothed``).
        pixel: (n,) int32 linear pixel index of each sample.
        max_gap: how far to look (px).
        self_gap: a sample of the same curve counts only beyond this distance.
        bump_contrast: grey levels of rise and fall that make a bump.
        step: marching step (px); the 2 x 2 pixels around each step are read, so
            steps below 0.5 px cannot jump over an 8-connected line.

    Returns:
        (neighbour (n, 2) int32, gap (n, 2) float32, bump (n, 2) int32) on uv's device.

    Size: a public function: the sample arrays and its documented keyword-only options, one per setting of the
    march.
    """
    n = uv.shape[0] if isinstance(uv, wp.array) else -1
    for name, a, dt in (("uv", uv, wp.vec2), ("normal", normal, wp.vec2), ("piece", piece, wp.int32),
                        ("pixel", pixel, wp.int32)):
        if not isinstance(a, wp.array) or a.dtype != dt or a.shape != (n,):
            raise ValueError(f"link_lines: {name} must be a ({n},) {dt.__name__} Warp array")
    if not isinstance(image, wp.array) or image.ndim != 2 or image.dtype != wp.float32:
        raise ValueError("link_lines: image must be an (H, W) float32 Warp array")
    if not (max_gap > 0 and 0 < step <= 0.5 and bump_contrast > 0):
        raise ValueError(f"link_lines: need max_gap > 0, 0 < step <= 0.5 and bump_contrast > 0, got {max_gap}, "
                         f"{step}, {bump_contrast}")
    dev = uv.device
    height, width = image.shape
    smap = wp.full((height, width), -1, dtype=wp.int32, device=dev)
    neighbour = wp.empty((n, 2), dtype=wp.int32, device=dev)
    gap = wp.empty((n, 2), dtype=wp.float32, device=dev)
    bump = wp.empty((n, 2), dtype=wp.int32, device=dev)
    if n:
        pix = pixel.numpy()
        if pix.min() < 0 or pix.max() >= width * height:
            raise ValueError("link_lines: pixel index outside the image")
        wp.launch(scatter_samples_kernel, dim=n, inputs=[pixel], outputs=[smap.flatten()], device=dev)
        wp.launch(link_lines_kernel, dim=n, inputs=[uv, normal, piece, smap, image, float(max_gap), float(step),
                                                   float(self_gap), float(bump_contrast)],
                  outputs=[neighbour, gap, bump], device=dev)
    return neighbour, gap, bump
