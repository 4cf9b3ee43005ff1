"""The virtual rig's ray tracer: what the camera sees under a projector frame
(docs/design.md §16).

Two passes: :func:`trace_geometry`, once per view, traces each camera pixel's ``S x S``
sub-pixel rays (OpenCV model with distortion) against the object mesh (a ``wp.Mesh``)
and the analytic reference plane z = 0, and stores per sub-sample the projector pixel
that lights the hit, its direct and ambient weights, and per pixel the truth (depth,
world point, facet normal, lit mask); :func:`shade_frame`, once per frame, turns those
into the recorded image (emitted light sampled on a grid finer than the projector
pixels, camera response, seeded noise, clamping, rounding). A pixel whose ray the
camera model cannot give sees nothing (docs/design.md §6). The facet normal decides
what faces the light and offsets the shadow ray; the shading normal is interpolated
from per-corner normals (``pipeline.simulate.scenes.corner_normals``). The model in
full, with its figures: docs/virtual_rig.md.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import warp as wp

from ringscan.kernels.geometry import (
    LIGHT_PARALLEL,
    CameraModel,
    LightModel,
    camera_ray,
    direction_to_light,
    light_pixel,
)

wp.set_module_options({"enable_backward": False})  # no gradients are taken here: no adjoint code to compile

RAY_MAX_T = wp.constant(1.0e7)
NO_HIT_T = wp.constant(1.0e30)

__all__ = [
    "TraceMesh",
    "ViewGeometry",
    "make_trace_mesh",
    "trace_geometry",
    "shade_frame",
    "DEFAULT_SHADOW_EPS_MM",
]

DEFAULT_SHADOW_EPS_MM = 2.0e-3


@wp.struct
class SurfaceHit:
    """Nearest hit of a ray: ``hit`` 0/1, distance ``t``, point, facet and shading normals,
    and the mesh face hit (-1: the plane)."""

    hit: int
    t: float
    point: wp.vec3
    ng: wp.vec3
    ns: wp.vec3
    face: int


# ----------------------------------------------------------------------------- helpers


@wp.func
def trace_ray(mesh: wp.uint64, has_mesh: int, corner_n: wp.array(dtype=wp.vec3), origin: wp.vec3, d: wp.vec3):
    """Nearest hit of the ray origin + t d (d unit) on the mesh or the plane z = 0."""
    h = SurfaceHit()
    h.hit = 0
    h.t = NO_HIT_T
    h.face = -1
    # Reference plane z = 0, opaque from both sides.
    if d[2] != 0.0:
        tp = -origin[2] / d[2]
        if tp > 0.0:
            h.hit = 1
            h.t = tp
            h.ng = wp.vec3(0.0, 0.0, 1.0)
            h.ns = h.ng
    if has_mesh != 0:
        q = wp.mesh_query_ray(mesh, origin, d, wp.min(h.t, RAY_MAX_T))
        if q.result and q.t < h.t:
            h.hit = 1
            h.t = q.t
            h.ng = wp.normalize(q.normal)
            h.face = q.face
            c = q.face * 3
            w2 = 1.0 - q.u - q.v
            ns = q.u * corner_n[c] + q.v * corner_n[c + 1] + w2 * corner_n[c + 2]
            if wp.length(ns) > 1.0e-12:
                h.ns = wp.normalize(ns)
            else:
                h.ns = h.ng
    if h.hit != 0:
        h.point = origin + h.t * d
        if wp.dot(h.ng, d) > 0.0:
            h.ng = -h.ng
            h.ns = -h.ns
    return h


@wp.func
def direct_light(
    mesh: wp.uint64, has_mesh: int, light: LightModel, h: SurfaceHit, shadow_eps: float
):
    """Direct-light factor max(0, n_s . l) at a hit, 0 when it faces away from the
    light or lies in a shadow (of the mesh, or of the plane z = 0)."""
    X = h.point
    L = direction_to_light(light, X)
    if wp.dot(h.ng, L) <= 0.0:
        return 0.0
    max_t = RAY_MAX_T
    if light.model != LIGHT_PARALLEL:
        max_t = wp.length(light.cam.center - X)
    o = X + shadow_eps * h.ng
    # The plane blocks the light when the segment to the light crosses z = 0.
    if L[2] != 0.0:
        tp = -o[2] / L[2]
        if tp > 0.0 and tp < max_t:
            return 0.0
    if has_mesh != 0:
        if wp.mesh_query_ray_anyhit(mesh, o, L, max_t):
            return 0.0
    return wp.max(0.0, wp.dot(h.ns, L))


@wp.func
def inside_image(u: float, v: float, w: int, hgt: int):
    """1 when (u, v) lies on the image [-0.5, w-0.5] x [-0.5, h-0.5], else 0."""
    if u >= -0.5 and u <= float(w) - 0.5 and v >= -0.5 and v <= float(hgt) - 0.5:
        return 1
    return 0


@wp.func
def sample_emitted(img: wp.array2d(dtype=float), u: float, v: float, k: int, linear: int):
    """Emitted light at projector position (u, v) from an image sampled k times finer
    than the projector's pixels (fine pixel centres at ((m + 0.5) / k - 0.5) + i);
    bilinear (``linear`` = 1) or nearest; 0 outside the projector image."""
    hgt = img.shape[0]
    w = img.shape[1]
    if inside_image(u, v, w / k, hgt / k) == 0:
        return 0.0
    uf = (u + 0.5) * float(k) - 0.5
    vf = (v + 0.5) * float(k) - 0.5
    if linear == 0:
        xn = wp.clamp(int(wp.floor(uf + 0.5)), 0, w - 1)
        yn = wp.clamp(int(wp.floor(vf + 0.5)), 0, hgt - 1)
        return img[yn, xn]
    x = wp.clamp(uf, 0.0, float(w - 1))
    y = wp.clamp(vf, 0.0, float(hgt - 1))
    x0 = int(wp.floor(x))
    y0 = int(wp.floor(y))
    x1 = wp.min(x0 + 1, w - 1)
    y1 = wp.min(y0 + 1, hgt - 1)
    fx = x - float(x0)
    fy = y - float(y0)
    top = (1.0 - fx) * img[y0, x0] + fx * img[y0, x1]
    bot = (1.0 - fx) * img[y1, x0] + fx * img[y1, x1]
    return (1.0 - fy) * top + fy * bot


# ----------------------------------------------------------------------------- kernels


@wp.kernel
def trace_geometry_kernel(
    mesh: wp.uint64,
    has_mesh: int,
    corner_n: wp.array(dtype=wp.vec3),
    face_albedo: wp.array(dtype=float),
    cam: CameraModel,
    light: LightModel,
    proj_w: int,
    proj_h: int,
    supersample: int,
    albedo: float,
    ambient: float,
    shadow_eps: float,
    samples: wp.array(dtype=wp.vec3),
    base: wp.array2d(dtype=float),
    depth: wp.array2d(dtype=float),
    points: wp.array2d(dtype=wp.vec3),
    normals: wp.array2d(dtype=wp.vec3),
    lit: wp.array2d(dtype=wp.uint8),
):
    """Trace one view, one thread per camera pixel (dim = (H, W)).

    Args:
        corner_n: (3 M,) read: shading normal per face corner (face f, corner k at 3 f + k).
        face_albedo: (M,) or (0,) read: albedo of each face, replacing ``albedo`` on the
            mesh (empty: ``albedo`` everywhere; the plane always has ``albedo``).
        samples: (H * W * S * S,) written: (u_p, v_p, albedo * direct factor) per sub-sample,
            at index ((y * W + x) * S + j) * S + i.
        base: (H, W) written: mean over sub-samples of albedo * ambient * hit.
        depth: (H, W) written: centre ray's camera-frame Z_c (mm), NaN where no hit.
        points: (H, W) written: centre ray's world point, NaN where no hit.
        normals: (H, W) written: centre ray's facet normal (facing the camera), NaN where no hit.
        lit: (H, W) written: 1 where the centre ray hits a point lit by the projector image.

    Size: Warp kernels take each array, the mesh, the camera and the light as its own argument: two read, six
    written, and the scene's scalar settings (projector size, supersampling, albedo, ambient, shadow offset).
    """
    y, x = wp.tid()
    width = depth.shape[1]
    origin = cam.center
    ss = supersample
    inv = 1.0 / float(ss)
    acc = float(0.0)
    for j in range(ss):
        for i in range(ss):
            u = float(x) + (float(i) + 0.5) * inv - 0.5
            v = float(y) + (float(j) + 0.5) * inv - 0.5
            d, ray_ok = camera_ray(cam, u, v)
            h = trace_ray(mesh, has_mesh, corner_n, origin, d)
            k = ((y * width + x) * ss + j) * ss + i
            s = wp.vec3(0.0, 0.0, 0.0)
            if h.hit != 0 and ray_ok:
                alb = albedo
                if h.face >= 0 and face_albedo.shape[0] > 0:
                    alb = face_albedo[h.face]
                acc += alb * ambient
                p = light_pixel(light, h.point)
                if p[2] > 0.0:
                    f = direct_light(mesh, has_mesh, light, h, shadow_eps)
                    s = wp.vec3(p[0], p[1], alb * f)
            samples[k] = s
    base[y, x] = acc * inv * inv

    nan = wp.nan
    d, ray_ok = camera_ray(cam, float(x), float(y))
    h = trace_ray(mesh, has_mesh, corner_n, origin, d)
    if h.hit != 0 and ray_ok:
        Xc = cam.R * h.point + cam.t
        depth[y, x] = Xc[2]
        points[y, x] = h.point
        normals[y, x] = h.ng
        p = light_pixel(light, h.point)
        is_lit = wp.uint8(0)
        if p[2] > 0.0 and inside_image(p[0], p[1], proj_w, proj_h) != 0:
            if direct_light(mesh, has_mesh, light, h, shadow_eps) > 0.0:
                is_lit = wp.uint8(1)
        lit[y, x] = is_lit
    else:
        depth[y, x] = nan
        points[y, x] = wp.vec3(nan, nan, nan)
        normals[y, x] = wp.vec3(nan, nan, nan)
        lit[y, x] = wp.uint8(0)


@wp.kernel
def shade_kernel(
    samples: wp.array(dtype=wp.vec3),
    base: wp.array2d(dtype=float),
    emitted: wp.array2d(dtype=float),
    upsample: int,
    linear: int,
    supersample: int,
    inv_full: float,
    inv_gamma: float,
    full_scale: float,
    noise_sigma: float,
    seed: int,
    out: wp.array2d(dtype=wp.uint16),
):
    """Shade one frame, one thread per camera pixel (dim = (H, W)).

    Args:
        samples: (H * W * S * S,) read: from :func:`trace_geometry_kernel`.
        base: (H, W) read: ambient irradiance per pixel.
        emitted: (Hp * k, Wp * k) read: emitted projector light, 0..1 (after response and
            defocus), sampled k = ``upsample`` times finer than the projector pixels.
        out: (H, W) written: recorded value, 0..full_scale.

    Size: Warp kernels take each array as its own argument: three read and one written, plus the scalars
    shade_frame derives from its options and the geometry's supersampling.
    """
    y, x = wp.tid()
    width = base.shape[1]
    ss = supersample
    n = ss * ss
    k0 = (y * width + x) * n
    acc = float(0.0)
    for k in range(n):
        s = samples[k0 + k]
        if s[2] > 0.0:
            acc += s[2] * sample_emitted(emitted, s[0], s[1], upsample, linear)
    irr = base[y, x] + acc / float(n)
    val = full_scale * wp.pow(wp.max(irr * inv_full, 0.0), inv_gamma)
    if noise_sigma > 0.0:
        state = wp.rand_init(seed, y * width + x)
        val += noise_sigma * wp.randn(state)
    val = wp.clamp(wp.floor(val + 0.5), 0.0, full_scale)
    out[y, x] = wp.uint16(int(val))


# ----------------------------------------------------------------------------- host


@dataclass
class TraceMesh:
    """An object mesh on a device, ready to trace (``mesh`` is None for no object)."""

    mesh: wp.Mesh | None
    """The BVH-backed Warp mesh (world frame, float32), or None (plane only)."""
    corner_normals: wp.array
    """(3 M,) vec3 shading normals per face corner (may be empty)."""
    face_albedo: wp.array
    """(M,) float32 albedo per face, or empty: the render's one albedo everywhere."""
    points: wp.array | None
    """(N,) vec3 vertex positions kept alive for the mesh."""
    indices: wp.array | None
    """(3 M,) int32 triangle indices kept alive for the mesh."""

    @property
    def device(self):
        return self.corner_normals.device


@dataclass
class ViewGeometry:
    """The result of :func:`trace_geometry` for one view (Warp arrays on its device)."""

    width: int
    height: int
    supersample: int
    samples: wp.array
    """(H * W * S * S,) vec3: u_p, v_p, direct weight per sub-sample."""
    base: wp.array
    """(H, W) float32 ambient irradiance."""
    depth: wp.array
    """(H, W) float32 camera-frame Z_c (mm), NaN where no hit."""
    points: wp.array
    """(H, W) vec3 world points, NaN where no hit."""
    normals: wp.array
    """(H, W) vec3 facet normals (facing the camera), NaN where no hit."""
    lit: wp.array
    """(H, W) uint8 1 = lit by the projector image."""

    @property
    def device(self):
        return self.base.device


def make_trace_mesh(vertices, faces, corner_normals, *, device, face_albedo=None) -> TraceMesh:
    """Upload a mesh for tracing.

    Args:
        vertices: (N, 3) float world positions (mm).
        faces: (M, 3) int vertex indices (M may be 0: no object).
        corner_normals: (M, 3, 3) shading normal per face corner.
        device: Warp device.
        face_albedo: (M,) albedo of each face in [0, 1] (a printed texture), or None:
            :func:`trace_geometry`'s one ``albedo`` everywhere.
    """
    v = np.asarray(vertices, np.float64)
    f = np.asarray(faces)
    cn = np.asarray(corner_normals, np.float64)
    if v.ndim != 2 or v.shape[1] != 3:
        raise ValueError(f"vertices: expected shape (N, 3), got {v.shape}")
    if f.ndim != 2 or f.shape[1] != 3 or f.dtype.kind not in "iu":
        raise ValueError(f"faces: expected integer shape (M, 3), got {f.shape} {f.dtype}")
    if cn.shape != (f.shape[0], 3, 3):
        raise ValueError(f"corner_normals: expected shape ({f.shape[0]}, 3, 3), got {cn.shape}")
    if f.size and (f.min() < 0 or f.max() >= v.shape[0]):
        raise ValueError(f"faces: indices must lie in [0, {v.shape[0]}), got [{f.min()}, {f.max()}]")
    if not np.all(np.isfinite(v)):
        raise ValueError("vertices: contain non-finite values")
    fa = np.zeros(0) if face_albedo is None else np.asarray(face_albedo, np.float64)
    if face_albedo is not None and (fa.shape != (f.shape[0],) or not np.all((fa >= 0) & (fa <= 1))):
        raise ValueError(f"face_albedo: expected shape ({f.shape[0]},) with values in [0, 1], got {fa.shape}"
                         + (f" in [{fa.min():g}, {fa.max():g}]" if fa.size and fa.ndim == 1 else ""))
    normals = wp.array(cn.reshape(-1, 3).astype(np.float32), dtype=wp.vec3, device=device)
    albedo = wp.array(fa.astype(np.float32), dtype=float, device=device)
    if f.shape[0] == 0:
        return TraceMesh(mesh=None, corner_normals=normals, face_albedo=albedo, points=None, indices=None)
    pts = wp.array(v.astype(np.float32), dtype=wp.vec3, device=device)
    idx = wp.array(f.astype(np.int32).ravel(), dtype=wp.int32, device=device)
    return TraceMesh(mesh=wp.Mesh(points=pts, indices=idx), corner_normals=normals, face_albedo=albedo, points=pts,
                     indices=idx)


def trace_geometry(
    scene: TraceMesh,
    camera: CameraModel,
    light: LightModel,
    *,
    width: int,
    height: int,
    projector_size: tuple[int, int],
    supersample: int = 2,
    albedo: float = 0.8,
    ambient: float = 0.05,
    shadow_eps: float = DEFAULT_SHADOW_EPS_MM,
) -> ViewGeometry:
    """Trace one view (the geometry pass) on the scene's device.

    Args:
        scene: from :func:`make_trace_mesh`.
        camera, light: Warp structs from ``kernels.geometry``.
        width, height: camera image size (pixels).
        projector_size: (W_p, H_p), for the ``lit`` mask.
        supersample: S, sub-samples per pixel side (S * S per pixel).
        albedo: surface reflectance (0..1]: of the plane, and of the mesh unless its
            faces carry their own (``make_trace_mesh(face_albedo=...)``).
        ambient: ambient irradiance relative to the projector's full white.
        shadow_eps: offset (mm) of a shadow ray's origin along the facet normal.

    Size: a public function: the scene, camera and light and its documented keyword-only options, one per
    user-facing setting of the geometry pass.
    """
    if width <= 0 or height <= 0:
        raise ValueError(f"camera size must be positive, got {width}x{height}")
    if supersample < 1:
        raise ValueError(f"supersample must be >= 1, got {supersample}")
    pw, ph = (int(x) for x in projector_size)
    if pw <= 0 or ph <= 0:
        raise ValueError(f"projector_size must be positive, got {projector_size}")
    dev = scene.device
    shape = (height, width)
    geo = ViewGeometry(
        width=width,
        height=height,
        supersample=supersample,
        samples=wp.empty(height * width * supersample * supersample, dtype=wp.vec3, device=dev),
        base=wp.empty(shape, dtype=float, device=dev),
        depth=wp.empty(shape, dtype=float, device=dev),
        points=wp.empty(shape, dtype=wp.vec3, device=dev),
        normals=wp.empty(shape, dtype=wp.vec3, device=dev),
        lit=wp.empty(shape, dtype=wp.uint8, device=dev),
    )
    mesh_id = scene.mesh.id if scene.mesh is not None else wp.uint64(0)
    wp.launch(
        trace_geometry_kernel,
        dim=shape,
        inputs=[mesh_id, int(scene.mesh is not None), scene.corner_normals, scene.face_albedo, camera, light,
                pw, ph, int(supersample), float(albedo), float(ambient), float(shadow_eps)],
        outputs=[geo.samples, geo.base, geo.depth, geo.points, geo.normals, geo.lit],
        device=dev,
    )
    return geo


def shade_frame(
    geometry: ViewGeometry,
    emitted: wp.array,
    *,
    full_irradiance: float,
    upsample: int = 1,
    interpolation: str = "linear",
    gamma: float = 1.0,
    full_scale: int = 255,
    noise_sigma: float = 0.0,
    seed: int = 0,
) -> wp.array:
    """Shade one frame (the shading pass) on the geometry's device.

    Args:
        geometry: from :func:`trace_geometry`.
        emitted: (H_p * k, W_p * k) float32 emitted light, 0..1, on the same device.
        upsample: k, how many times finer than the projector's pixels ``emitted`` is sampled.
        interpolation: ``linear`` (bilinear between samples) or ``nearest`` (a
            piecewise-constant image: sharp projector pixels).
        full_irradiance: the irradiance recorded as ``full_scale``.
        gamma: camera response: recorded = full_scale * (I / full_irradiance)^(1/gamma).
        full_scale: 255 (8-bit) or 65535 (16-bit).
        noise_sigma: Gaussian noise, in recorded units.
        seed: noise seed (31-bit).

    Returns:
        (H, W) uint16 Warp array of recorded values in 0..full_scale.

    Size: a public function: the geometry, the emitted light and its documented keyword-only options, one per
    user-facing setting of the camera's response and noise.
    """
    if emitted.ndim != 2 or emitted.dtype != wp.float32:
        raise ValueError(f"emitted: expected a 2D float32 array, got {emitted.ndim}D {emitted.dtype}")
    if str(emitted.device) != str(geometry.device):
        raise ValueError(f"emitted is on {emitted.device}, the geometry on {geometry.device}")
    if upsample < 1 or emitted.shape[0] % upsample or emitted.shape[1] % upsample:
        raise ValueError(f"upsample: {upsample} must be >= 1 and divide the emitted image's {emitted.shape}")
    if interpolation not in ("linear", "nearest"):
        raise ValueError(f"interpolation: expected 'linear' or 'nearest', got {interpolation!r}")
    if not full_irradiance > 0 or not gamma > 0:
        raise ValueError(f"full_irradiance and gamma must be > 0, got {full_irradiance}, {gamma}")
    if not 0 < full_scale <= 65535:
        raise ValueError(f"full_scale must be in 1..65535, got {full_scale}")
    out = wp.empty((geometry.height, geometry.width), dtype=wp.uint16, device=geometry.device)
    wp.launch(
        shade_kernel,
        dim=(geometry.height, geometry.width),
        inputs=[geometry.samples, geometry.base, emitted, int(upsample), int(interpolation == "linear"),
                int(geometry.supersample), 1.0 / float(full_irradiance),
                1.0 / float(gamma), float(full_scale), float(noise_sigma), int(seed) & 0x7FFFFFFF],
        outputs=[out],
        device=geometry.device,
    )
    return out
