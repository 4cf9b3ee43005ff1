"""Colour maps, colour bars, heat maps and ring overlays for previews."""

from __future__ import annotations

import logging
import math
import os

import numpy as np

from ringscan.pipeline.formats.images import write_image

log = logging.getLogger(__name__)

__all__ = ["colorize", "colorbar", "colorbar_labels", "nice_ticks", "readable_unit", "category_colours",
           "ring_overlay", "heatmap", "depth_heatmap", "error_heatmap"]

NICE_STEPS = (1.0, 2.0, 2.5, 5.0, 10.0)
"""Tick steps within a decade: ticks read as round numbers (0.002, 0.025, 50), never 0.00409."""
SMALLER_UNIT = {"mm": ("um", 1000.0)}
"""A length unit and the one below it with its factor: a scale that tops out under 0.1 mm reads in um."""


def _diverging(x: np.ndarray) -> np.ndarray:
    """Blue - white - red for x in [0, 1] (RGB, 0..1)."""
    x = np.clip(x, 0, 1)[..., None]
    blue = np.array([0.23, 0.30, 0.75])
    white = np.array([0.95, 0.95, 0.95])
    red = np.array([0.71, 0.02, 0.15])
    lo = blue + (white - blue) * (x / 0.5)
    hi = white + (red - white) * ((x - 0.5) / 0.5)
    return np.where(x < 0.5, lo, hi)


def _cmap_rgb(x: np.ndarray, cmap: str) -> np.ndarray:
    """Colour map values x in [0, 1] -> RGB float (..., 3)."""
    import cv2

    if cmap == "diverging":
        return _diverging(np.where(np.isfinite(x), x, 0.5))
    maps = {"turbo": cv2.COLORMAP_TURBO, "viridis": cv2.COLORMAP_VIRIDIS, "inferno": cv2.COLORMAP_INFERNO,
            "jet": cv2.COLORMAP_JET}
    if cmap not in maps:
        raise ValueError(f"unknown colour map {cmap!r}; use one of {', '.join([*maps, 'diverging'])}")
    x = np.asarray(x, float)
    idx = np.clip(np.rint(np.where(np.isfinite(x), x, 0.0) * 255), 0, 255).astype(np.uint8)
    lut = cv2.applyColorMap(np.arange(256, dtype=np.uint8)[:, None], maps[cmap])[:, 0, ::-1] / 255.0
    return lut[idx]


def colorize(geom, values: np.ndarray, *, vmin: float | None = None, vmax: float | None = None,
             cmap: str = "turbo"):
    """Paint a cloud's points (or a mesh's vertices) by ``values``; returns a copy.

    NaN values are painted grey. The scale is [vmin, vmax] (default: the 1st and
    99th percentiles).
    """
    import open3d as o3d

    is_mesh = hasattr(geom, "triangles")
    n = len(geom.vertices) if is_mesh else len(geom.points)
    values = np.asarray(values, float)
    if values.shape != (n,):
        raise ValueError(f"values must have shape ({n},), got {values.shape}")
    vmin, vmax = _range(values, vmin, vmax)
    rgb = _cmap_rgb((values - vmin) / (vmax - vmin), cmap)
    rgb[~np.isfinite(values)] = 0.5
    out = o3d.geometry.TriangleMesh(geom) if is_mesh else o3d.geometry.PointCloud(geom)
    if is_mesh:
        out.vertex_colors = o3d.utility.Vector3dVector(rgb)
    else:
        out.colors = o3d.utility.Vector3dVector(rgb)
    return out


def _range(values: np.ndarray, vmin, vmax) -> tuple[float, float]:
    fin = values[np.isfinite(values)]
    if vmin is None:
        vmin = float(np.quantile(fin, 0.01)) if len(fin) else 0.0
    if vmax is None:
        vmax = float(np.quantile(fin, 0.99)) if len(fin) else 1.0
    if not vmax > vmin:
        vmax = vmin + 1e-9 if vmax == vmin else vmin + 1.0
    return float(vmin), float(vmax)


def nice_ticks(vmin: float, vmax: float, n: int = 5) -> tuple[np.ndarray, list[str]]:
    """About ``n`` round tick values inside [vmin, vmax] (a step of 1, 2, 2.5 or 5 times a power of ten)
    and their labels, all in one format (the step's decimals): ``0, 0.002, 0.004``, never ``0.00409``."""
    vmin, vmax = float(vmin), float(vmax)
    if not (np.isfinite(vmin) and np.isfinite(vmax)) or vmax <= vmin:
        return np.array([vmin]), [f"{vmin:g}"]
    e = math.floor(math.log10((vmax - vmin) / max(n - 1, 1)))

    def count(step):
        return math.floor(vmax / step + 1e-9) - math.ceil(vmin / step - 1e-9) + 1

    steps = [m * 10.0 ** k for k in (e - 1, e, e + 1) for m in NICE_STEPS[:-1]]
    step = min(steps, key=lambda s: (abs(count(s) - n), -s))  # the count nearest n, then the larger step
    first = math.ceil(vmin / step - 1e-9)
    ticks = np.array([k * step for k in range(first, math.floor(vmax / step + 1e-9) + 1)])
    mant = step / 10.0 ** math.floor(math.log10(step))
    decimals = max(0, -math.floor(math.log10(step)) + (1 if abs(mant - 2.5) < 1e-9 else 0))
    labels = [f"{0.0 if abs(v) < step * 1e-9 else v:.{decimals}f}" for v in ticks]
    return ticks, labels


def readable_unit(vmax: float, unit: str = "mm") -> tuple[str, float]:
    """The unit a scale reaching ``vmax`` (in ``unit``) reads best in, and the factor to it: mm below
    0.1 mm -> um (x1000), so that ticks are 0, 2, 4 um and not 0.00409 mm; otherwise ``unit`` itself."""
    if unit in SMALLER_UNIT and 0 < abs(vmax) < 0.1:
        return SMALLER_UNIT[unit]
    return unit, 1.0


def category_colours(n: int) -> np.ndarray:
    """``n`` well-separated colours (RGB, 0..1), one a category: matplotlib's tab10 then tab20's light ones."""
    base = np.array([[31, 119, 180], [255, 127, 14], [44, 160, 44], [214, 39, 40], [148, 103, 189],
                     [140, 86, 75], [227, 119, 194], [127, 127, 127], [188, 189, 34], [23, 190, 207],
                     [174, 199, 232], [255, 187, 120], [152, 223, 138], [255, 152, 150], [197, 176, 213],
                     [196, 156, 148], [247, 182, 210], [199, 199, 199], [219, 219, 141], [158, 218, 229]]) / 255.0
    return base[np.arange(n) % len(base)]


def colorbar_labels(*, vmin: float = 0.0, vmax: float = 1.0, categories=None, **_) -> list[str]:
    """The labels :func:`colorbar` draws for these arguments (tick labels, or the categories' names)."""
    if categories is not None:
        return [str(name) for name, _ in categories]
    return nice_ticks(vmin, vmax)[1]


def colorbar(height: int, *, vmin: float = 0.0, vmax: float = 1.0, cmap: str = "turbo", label: str = "",
             width: int = 110, background=(1.0, 1.0, 1.0), categories=None) -> np.ndarray:
    """A vertical colour bar (BGR uint8, height x width): round ticks in one format
    (:func:`nice_ticks`) and a title; or, with ``categories`` [(name, RGB 0..1), ...], a legend: one
    swatch and name a category (views, rings: no continuous scale between them)."""
    import cv2

    bg = np.clip(np.rint(np.asarray(background, float)[::-1] * 255), 0, 255).astype(np.uint8)
    bar = np.empty((height, width, 3), np.uint8)
    bar[:] = bg
    roomy = height >= 90
    top, bottom = (28, height - 14) if roomy else (4, height - 4)
    if bottom - top < 4:
        return bar
    ink = (0, 0, 0) if bg.mean() > 127 else (255, 255, 255)
    if categories is not None:
        if label and roomy:
            cv2.putText(bar, label[:16], (4, 16), cv2.FONT_HERSHEY_SIMPLEX, 0.42, ink, 1, cv2.LINE_AA)
        row = max(8, min(18, (bottom - top) // max(len(categories), 1)))
        for k, (name, rgb) in enumerate(categories[: (bottom - top) // row]):
            y = top + k * row
            colour = tuple(int(c) for c in np.clip(np.rint(np.asarray(rgb, float)[::-1] * 255), 0, 255))
            cv2.rectangle(bar, (8, y + 2), (22, y + row - 3), colour, -1)
            cv2.putText(bar, str(name)[:12], (27, y + row - 5), cv2.FONT_HERSHEY_SIMPLEX, 0.36, ink, 1, cv2.LINE_AA)
        return bar
    x0, x1 = 10, 30
    ramp = np.linspace(1, 0, bottom - top)
    rgb = _cmap_rgb(ramp, cmap)
    bar[top:bottom, x0:x1] = np.clip(np.rint(rgb[:, None, ::-1] * 255), 0, 255).astype(np.uint8)
    bar[top:bottom, x0 - 1] = bar[top:bottom, x1] = 0
    bar[top - 1, x0 - 1:x1 + 1] = bar[bottom, x0 - 1:x1 + 1] = 0
    for val, txt in zip(*nice_ticks(vmin, vmax)):
        f = (val - vmin) / (vmax - vmin) if vmax > vmin else 0.0
        y = int(round(bottom - 1 - f * (bottom - top - 1)))
        bar[y, x1:x1 + 5] = 0
        cv2.putText(bar, txt, (x1 + 8, min(max(y + 4, 10), height - 2)), cv2.FONT_HERSHEY_SIMPLEX, 0.38, ink, 1,
                    cv2.LINE_AA)
    if label and roomy:
        cv2.putText(bar, label[:16], (4, 16), cv2.FONT_HERSHEY_SIMPLEX, 0.42, ink, 1, cv2.LINE_AA)
    return bar


def _grey_bgr(image: np.ndarray) -> np.ndarray:
    img = np.asarray(image)
    if img.ndim == 3 and img.shape[2] in (3, 4):
        img = img[:, :, :3].astype(np.float64).mean(axis=2)
    elif img.ndim != 2:
        raise ValueError(f"image must be 2D grey or (H, W, 3) colour, got shape {img.shape}")
    img = img.astype(np.float64)
    full = 65535.0 if np.asarray(image).dtype == np.uint16 else (255.0 if np.asarray(image).dtype == np.uint8
                                                                  else max(float(img.max()), 1e-9))
    g = np.clip(np.rint(img / full * 255), 0, 255).astype(np.uint8)
    return np.repeat(g[:, :, None], 3, axis=2)


def _ring_palette(n: int) -> np.ndarray:
    """n well-separated BGR colours (golden-ratio hues), neighbouring rings differ."""
    import cv2

    h = (np.arange(n) * 0.618033988749895) % 1.0
    hsv = np.stack([np.rint(h * 179), np.full(n, 230), np.full(n, 255)], axis=1).astype(np.uint8)[None]
    return cv2.cvtColor(hsv, cv2.COLOR_HSV2BGR)[0]


def ring_overlay(image: np.ndarray, u: np.ndarray, v: np.ndarray, ring: np.ndarray, *, radius: int = 1,
                 dim: float = 0.6, out: str | os.PathLike | None = None) -> np.ndarray:
    """Draw decoded ring samples over a camera image.

    Args:
        image: the camera image (2D grey uint8/uint16, or (H, W, 3) colour).
        u, v: sample positions in pixels (sub-pixel allowed; rounded to draw).
        ring: per sample the ring/band index (integers: each ring its own colour,
            neighbours well apart) or ``rho`` (floats: turbo colour map, with a bar).
        radius: dot radius in pixels (0: single pixels).
        dim: the image is darkened to this fraction so the colours stand out.
        out: write the picture to this PNG as well.

    Returns:
        The overlay, BGR uint8 (wider than the image when a colour bar is added).
    """
    u = np.asarray(u, float).ravel()
    v = np.asarray(v, float).ravel()
    ring = np.asarray(ring).ravel()
    if not (len(u) == len(v) == len(ring)):
        raise ValueError(f"u, v and ring must have one length, got {len(u)}, {len(v)}, {len(ring)}")
    base = np.rint(_grey_bgr(image) * float(dim)).astype(np.uint8)
    H, W = base.shape[:2]
    ok = np.isfinite(u) & np.isfinite(v)
    if ring.dtype.kind == "f":
        ok &= np.isfinite(ring)
    u, v, ring = u[ok], v[ok], ring[ok]
    bar = None
    if ring.dtype.kind in "iub":
        r = ring.astype(np.int64)
        lo = int(r.min()) if len(r) else 0
        pal = _ring_palette(int(r.max()) - lo + 1 if len(r) else 1)
        col = pal[r - lo]
    else:
        vmin, vmax = _range(ring.astype(float), None, None) if len(ring) else (0.0, 1.0)
        col = np.clip(np.rint(_cmap_rgb((ring - vmin) / (vmax - vmin), "turbo")[:, ::-1] * 255), 0,
                      255).astype(np.uint8)
        bar = colorbar(H, vmin=vmin, vmax=vmax, cmap="turbo", label="rho (px)", background=(0, 0, 0))
    ui = np.rint(u).astype(np.int64)
    vi = np.rint(v).astype(np.int64)
    for dy in range(-radius, radius + 1):
        for dx in range(-radius, radius + 1):
            if dx * dx + dy * dy > radius * radius + radius:
                continue
            x, y = ui + dx, vi + dy
            inside = (x >= 0) & (x < W) & (y >= 0) & (y < H)
            base[y[inside], x[inside]] = col[inside]
    if bar is not None:
        base = np.concatenate([base, bar], axis=1)
    if out is not None:
        write_image(out, base)
    return base


def heatmap(values: np.ndarray, *, vmin: float | None = None, vmax: float | None = None, cmap: str = "turbo",
            label: str = "", out: str | os.PathLike | None = None) -> np.ndarray:
    """Colour-map a 2D array (NaN or inf = no data, drawn dark grey) with a colour bar.

    The scale is [vmin, vmax] (default: 1st to 99th percentile of the finite values).
    Returns BGR uint8 of shape (H, W + 110, 3); also written to ``out`` when given.
    """
    a = np.asarray(values, dtype=np.float64)
    if a.ndim != 2 or a.size == 0:
        raise ValueError(f"values must be a non-empty 2D array, got shape {a.shape}")
    vmin, vmax = _range(a, vmin, vmax)
    rgb = _cmap_rgb((a - vmin) / (vmax - vmin), cmap)
    bgr = np.clip(np.rint(rgb[:, :, ::-1] * 255), 0, 255).astype(np.uint8)
    bgr[~np.isfinite(a)] = 40
    bar = colorbar(a.shape[0], vmin=vmin, vmax=vmax, cmap=cmap, label=label, background=(1, 1, 1))
    img = np.concatenate([bgr, bar], axis=1)
    if out is not None:
        write_image(out, img)
    return img


def depth_heatmap(depth: np.ndarray, *, out: str | os.PathLike | None = None, unit: str = "mm",
                  vmin: float | None = None, vmax: float | None = None) -> np.ndarray:
    """Heat map of a depth map (0, NaN or inf = no data), turbo colour map."""
    d = np.asarray(depth, dtype=np.float64).copy()
    d[d == 0] = np.nan
    return heatmap(d, vmin=vmin, vmax=vmax, cmap="turbo", label=f"depth ({unit})", out=out)


def error_heatmap(error: np.ndarray, *, out: str | os.PathLike | None = None, unit: str = "mm",
                  limit: float | None = None) -> np.ndarray:
    """Heat map of a signed error map: blue (negative) - white (0) - red (positive),
    symmetric about 0 (``limit``: default the 99th percentile of |error|)."""
    e = np.asarray(error, dtype=np.float64)
    if limit is None:
        fin = np.abs(e[np.isfinite(e)])
        limit = float(np.quantile(fin, 0.99)) if len(fin) else 1.0
    limit = max(float(limit), 1e-12)
    return heatmap(e, vmin=-limit, vmax=limit, cmap="diverging", label=f"error ({unit})", out=out)
