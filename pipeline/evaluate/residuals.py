"""The residual map of a reconstructed view: each point's residual (PLY
``residual``: RMS reprojection px with two cameras, the projector-side residual
with one) at its camera-1 pixel, where a rig that does not fit its images shows
(docs/reconstruction.md "Two cameras")."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ringscan.pipeline.formats.atomic import atomic_path

__all__ = ["ResidualMap", "residual_map", "residual_map_figure", "plot_residuals", "NO_POINT_LABEL"]


@dataclass
class ResidualMap:
    """Per camera-1 pixel, the median residual of the points there (NaN: none)."""

    residual: np.ndarray
    """(H, W) float64 median residual of the points of each pixel."""
    summary: dict
    """points, median and p95 of the residuals, and the view's calibration check if known."""


def residual_map(fields: dict[str, np.ndarray], *, width: int, height: int, check: dict | None = None) -> ResidualMap:
    """Bin a view's points by their camera-1 pixel.

    Args:
        fields: a view's PLY fields (``u``, ``v``, ``residual``).
        width, height: camera 1's image size.
        check: the view's ``calibration_check`` from report.json, for the summary.

    Raises:
        ValueError: the cloud has no ``residual`` (made before residuals were written) or no ``u``, ``v``.
    """
    missing = [k for k in ("u", "v", "residual") if k not in fields]
    if missing:
        raise ValueError(f"the cloud has no {', '.join(missing)} (a view's PLY from ringscan reconstruct has them)")
    u = np.floor(np.asarray(fields["u"], np.float64) + 0.5).astype(np.int64)
    v = np.floor(np.asarray(fields["v"], np.float64) + 0.5).astype(np.int64)
    r = np.asarray(fields["residual"], np.float64)
    ok = (u >= 0) & (u < width) & (v >= 0) & (v < height) & np.isfinite(r) & (r >= 0)
    u, v, r = u[ok], v[ok], r[ok]
    out = np.full((height, width), np.nan)
    if r.size:
        key = v * width + u
        order = np.lexsort((r, key))
        key, rs = key[order], r[order]
        starts = np.flatnonzero(np.r_[True, key[1:] != key[:-1]])
        ends = np.r_[starts[1:], key.size]
        # the median of each pixel's sorted residuals
        med = 0.5 * (rs[starts + (ends - starts - 1) // 2] + rs[starts + (ends - starts) // 2])
        out.reshape(-1)[key[starts]] = med
    summ = {"points": int(r.size), "median": float(np.median(r)) if r.size else None,
            "p95": float(np.percentile(r, 95)) if r.size else None}
    if check:
        summ["calibration_check"] = check
    return ResidualMap(residual=out, summary=summ)


NO_POINT_LABEL = "no point (not decoded: e.g. a board's dark squares)"
"""The legend's name for the hatched pixels of a residual map."""


def residual_map_figure(rmap: ResidualMap, *, title: str = "", unit: str = "px"):
    """The map on a logarithmic colour scale with a colour bar; pixels without a point hatched grey
    (not white: white reads as a value) and named in a legend."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.colors import LogNorm
    from matplotlib.patches import Patch, Rectangle

    vals = rmap.residual[np.isfinite(rmap.residual) & (rmap.residual > 0)]
    lo, hi = (float(np.percentile(vals, 1)), float(np.percentile(vals, 99))) if vals.size else (1e-3, 1.0)
    lo = max(lo, 1e-6)
    hi = max(hi, lo * 10)
    h, w = rmap.residual.shape
    fig, ax = plt.subplots(figsize=(8, 8 * h / w + 0.8), constrained_layout=True)
    hatch = {"facecolor": "0.92", "edgecolor": "0.6", "hatch": "///", "linewidth": 0}
    ax.add_patch(Rectangle((-0.5, -0.5), w, h, zorder=0, **hatch))
    im = ax.imshow(np.ma.masked_invalid(np.maximum(rmap.residual, lo)), cmap="inferno", norm=LogNorm(vmin=lo, vmax=hi),
                   zorder=1)
    ax.set_xlabel("camera 1 u (px)")
    ax.set_ylabel("camera 1 v (px)")
    fig.colorbar(im, ax=ax, shrink=0.8, label=f"residual per point ({unit})")
    if not np.isfinite(rmap.residual).all():
        ax.legend(handles=[Patch(label=NO_POINT_LABEL, **hatch)], loc="lower right", fontsize=8)
    s = rmap.summary
    line = f"{s['points']} points" + (f", median {s['median']:.3g} {unit}, p95 {s['p95']:.3g} {unit}"
                                      if s["median"] is not None else "")
    c = s.get("calibration_check")
    if c:
        line += f"\n{c['kind']} check: median {c['median_px']:.3g} px, p95 {c['p95_px']:.3g} px" + (
            "" if c.get("fits", True) else " - the rig file does not fit the images")
    ax.set_title((title + "\n" if title else "") + line)
    return fig


def plot_residuals(rmap: ResidualMap, out: str | Path, *, title: str = "", unit: str = "px") -> Path:
    """:func:`residual_map_figure` written as PNG or SVG by the extension, atomically."""
    import matplotlib.pyplot as plt

    out = Path(out)
    fig = residual_map_figure(rmap, title=title, unit=unit)
    with atomic_path(out) as tmp:
        fig.savefig(tmp, dpi=80, format=out.suffix.lstrip(".").lower() or "png")
    plt.close(fig)
    return out
