"""Where a rig is blind, before scanning: per camera pixel, the predicted depth
standard deviation of a point on a reference surface with the ring constraint
alone, the angle alone, and both (docs/reconstruction.md, "Conditioning map").

Each camera ray meets the plane z = ``plane_z`` (the middle of the working volume by default);
the projector pixel lighting that point gives its rho and polar angle, and the
triangulation kernel itself, fed with those exact coordinates and the codec's
predicted standard deviations, says how well each constraint pins the point along
the ray (``Triangulation.sigma``) and where it drops it (grazing, ill-conditioned).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import warp as wp

from ringscan.kernels import init_warp, resolve_device
from ringscan.kernels.triangulation import TriangulateSettings, triangulate_rings
from ringscan.pipeline.formats.atomic import atomic_path
from ringscan.pipeline.formats.rig import Rig
from ringscan.pipeline.geometry import camera_model_for, camera_rays, light_model_for, projector_pixels

log = logging.getLogger(__name__)

__all__ = ["ConditioningSettings", "ConditioningMap", "compute_conditioning", "plot_conditioning", "MAX_MAP_PIXELS",
           "map_step_needed", "conditioning_figure", "empty_panel_reason"]

CONSTRAINT_PANELS = ("rings", "angle", "both")

MAX_MAP_PIXELS = 2_000_000
"""Most camera pixels a conditioning map evaluates: ~1.5 GB of memory (measured ~0.72 KB a pixel, the default
1280x1024 rig at step 1: 1.3 million pixels, 0.94 GB); a larger camera needs a larger step."""


def map_step_needed(width: int, height: int) -> int:
    """The least step at which a ``width`` x ``height`` camera's map has at most :data:`MAX_MAP_PIXELS` pixels."""
    step = 1
    while -(-width // step) * -(-height // step) > MAX_MAP_PIXELS:
        step += 1
    return step


@dataclass(frozen=True)
class ConditioningSettings:
    """Settings of the conditioning map."""

    plane_z: float | None = None
    """World z (mm) of the plane the camera rays are taken to meet; None: the middle
    of the rig's working volume (the reference plane z = 0 is usually its floor,
    where a point is as likely outside the volume as inside)."""
    step: int = 4
    """Camera pixels between evaluated pixels, in both directions (1: every pixel)."""
    sigma_rho_px: float = 0.01
    """Standard deviation of rho (projector px) assumed for the ring constraint."""
    sigma_tan_px: float = 0.05
    """Standard deviation of the tangential position (projector px) assumed for the angle."""
    triangulate: TriangulateSettings = field(default_factory=TriangulateSettings)
    """Thresholds that decide where a point is dropped (``min_incidence_cos``)."""


@dataclass
class ConditioningMap:
    """Predicted depth standard deviation per evaluated camera pixel."""

    sigma: dict
    """constraint (rings, angle, both) -> (h, w) float32 sigma along the ray (mm), NaN where dropped or unlit."""
    lit: np.ndarray
    """(h, w) bool: the plane point is lit by the coded annulus of the pattern."""
    step: int
    """Camera pixels between evaluated pixels."""
    plane_z: float
    """World z (mm) of the plane evaluated."""

    def summary(self) -> dict:
        """Share of lit pixels each constraint places, and its median sigma (mm)."""
        n = max(int(self.lit.sum()), 1)
        out = {}
        for k, s in self.sigma.items():
            v = s[self.lit & np.isfinite(s)]
            out[k] = {"placed": float(v.size / n), "median_sigma_mm": float(np.median(v)) if v.size else None}
        return out


def compute_conditioning(rig: Rig, *, center, rho_range: tuple[float, float], sector_bits: int = 6,
                         settings: ConditioningSettings = ConditioningSettings(), device: str | None = None
                         ) -> ConditioningMap:
    """The conditioning map of a rig and a pattern annulus.

    Args:
        rig: the rig.
        center: the pattern centre (c_u, c_v), projector px.
        rho_range: (inner, outer) radius of the coded annulus, projector px.
        sector_bits: the sector code's bits (the ring constraint's root choice).
        settings: plane, sampling and standard deviations.
        device: Warp device (None: the best available).
    """
    if settings.step < 1:
        raise ValueError(f"conditioning: step must be >= 1, got {settings.step}")
    if not (settings.sigma_rho_px > 0 and settings.sigma_tan_px > 0):
        raise ValueError("conditioning: sigma_rho_px and sigma_tan_px must be > 0")
    cam = rig.camera
    need = map_step_needed(cam.width, cam.height)
    if settings.step < need:
        raise ValueError(f"conditioning: step {settings.step} evaluates {-(-cam.width // settings.step)}x"
                         f"{-(-cam.height // settings.step)} pixels of the {cam.width}x{cam.height} camera: more than "
                         f"the {MAX_MAP_PIXELS} a map may have (~1.5 GB); a step of {need} or more fits")
    init_warp()
    device = resolve_device(device)
    ys, xs = np.mgrid[0:cam.height:settings.step, 0:cam.width:settings.step]
    uv = np.c_[xs.ravel(), ys.ravel()].astype(np.float64)
    C, d = camera_rays(rig, uv)
    vol = rig.volume
    plane_z = 0.5 * (vol.z_min + vol.z_max) if settings.plane_z is None else float(settings.plane_z)
    with np.errstate(divide="ignore", invalid="ignore"):
        t = (plane_z - C[2]) / d[:, 2]
    X = C + t[:, None] * d
    p = projector_pixels(rig, X)
    off = p - np.asarray(center, np.float64)
    rho = np.hypot(off[:, 0], off[:, 1])
    phi = np.arctan2(off[:, 1], off[:, 0])
    lit = np.isfinite(rho) & (t > 0) & (rho >= rho_range[0]) & (rho <= rho_range[1])
    if hasattr(rig.light, "width"):
        lit &= (p[:, 0] >= -0.5) & (p[:, 0] <= rig.light.width - 0.5) & (p[:, 1] >= -0.5) & (p[:, 1] <= rig.light.height - 0.5)
    sector = np.floor((phi + np.pi) / (2 * np.pi) * 2 ** sector_bits).astype(np.int32) if sector_bits else \
        np.full(rho.size, -1, np.int32)
    idx = np.flatnonzero(lit)
    n = idx.size
    sig = {}
    for k in CONSTRAINT_PANELS:
        out = np.full(rho.size, np.nan, np.float32)
        if n:
            ts = TriangulateSettings(**{**settings.triangulate.__dict__, "constraint": k})
            T = triangulate_rings(
                wp.array(uv[idx].astype(np.float32), dtype=wp.vec2, device=device),
                wp.array(rho[idx].astype(np.float32), device=device), wp.array(sector[idx], device=device),
                wp.ones(n, dtype=wp.float32, device=device), camera=camera_model_for(rig),
                light=light_model_for(rig), volume=(vol.z_min, vol.z_max, vol.r_max), center=tuple(center),
                sector_bits=sector_bits, phi=wp.array(phi[idx].astype(np.float32), device=device),
                sigma_rho=wp.full(n, settings.sigma_rho_px, dtype=wp.float32, device=device),
                sigma_tan=wp.full(n, settings.sigma_tan_px, dtype=wp.float32, device=device), settings=ts)
            st = T.status.numpy()
            s = T.sigma.numpy()
            out[idx] = np.where(st == 0, s, np.nan)
        sig[k] = out.reshape(xs.shape)
    return ConditioningMap(sigma=sig, lit=lit.reshape(xs.shape), step=settings.step, plane_z=plane_z)


def empty_panel_reason(cmap: ConditioningMap, constraint: str) -> str | None:
    """Why a panel of the map has no value, in words (None: it has some)."""
    if np.isfinite(cmap.sigma[constraint]).any():
        return None
    if not cmap.lit.any():
        return f"no camera pixel sees the coded rings on the plane z = {cmap.plane_z:g} mm"
    return f"the '{constraint}' constraint places none of the {int(cmap.lit.sum())} lit pixels"


def conditioning_figure(cmap: ConditioningMap, *, title: str = "", empty_why: str = ""):
    """The map's figure: three panels (rings, angle, both) on one logarithmic colour scale with a
    colour bar; unlit pixels light grey, lit pixels a constraint drops black (both in the legend). A
    panel with no value says so on the panel, and why (``empty_why`` first when given: what the caller
    knows, e.g. the scan's codec has no rings)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.colors import ListedColormap, LogNorm
    from matplotlib.patches import Patch

    vals = np.concatenate([s[np.isfinite(s)] for s in cmap.sigma.values()])
    lo, hi = (float(np.percentile(vals, 1)), float(np.percentile(vals, 99))) if vals.size else (1e-3, 1.0)
    lo, hi = max(lo, 1e-6), max(hi, lo * 10)
    h, w = cmap.lit.shape
    fig, axes = plt.subplots(1, 3, figsize=(15, 15 * h / (3 * w) + 1.2), constrained_layout=True)
    summ = cmap.summary()
    norm = LogNorm(vmin=lo, vmax=hi)
    im = None
    extent = (0, w * cmap.step, h * cmap.step, 0)
    for ax, k in zip(axes, CONSTRAINT_PANELS):
        # unlit: light grey; lit but dropped: black (under the sigma map)
        ax.imshow(np.where(cmap.lit, 0, 1), cmap=ListedColormap(["black", "0.85"]), vmin=0, vmax=1, extent=extent,
                  interpolation="nearest")
        im = ax.imshow(np.ma.masked_invalid(cmap.sigma[k]), cmap="viridis", norm=norm, extent=extent)
        s = summ[k]
        why = empty_panel_reason(cmap, k)
        if why is None:
            ax.set_title(f"{k}: {100 * s['placed']:.0f} % of lit pixels, median {s['median_sigma_mm']:.3g} mm")
        else:
            ax.set_title(f"{k}: no value")
            text = f"{empty_why}\n({why})" if empty_why else why
            ax.text(0.5, 0.5, "\n".join(_wrap(text, 38)), transform=ax.transAxes, ha="center", va="center",
                    fontsize=10, bbox={"facecolor": "white", "edgecolor": "0.3", "boxstyle": "round"})
        ax.set_xlabel("camera u (px)")
    axes[0].set_ylabel("camera v (px)")
    axes[-1].legend(handles=[Patch(color="0.85", label="not lit by the rings"),
                             Patch(color="black", label="lit, dropped by the constraint")],
                    loc="lower right", fontsize=8)
    fig.colorbar(im, ax=axes, shrink=0.8, label="predicted depth sigma along the ray (mm)")
    if title:
        fig.suptitle(title)
    return fig


def _wrap(text: str, width: int) -> list[str]:
    import textwrap

    return [ln for part in text.split("\n") for ln in textwrap.wrap(part, width)]


def plot_conditioning(cmap: ConditioningMap, out: str | Path, *, title: str = "", empty_why: str = "") -> Path:
    """:func:`conditioning_figure` written as PNG or SVG by the file's extension, atomically."""
    import matplotlib.pyplot as plt

    out = Path(out)
    fig = conditioning_figure(cmap, title=title, empty_why=empty_why)
    with atomic_path(out) as tmp:
        fig.savefig(tmp, dpi=80, format=out.suffix.lstrip(".").lower() or "png")
    plt.close(fig)
    return out
