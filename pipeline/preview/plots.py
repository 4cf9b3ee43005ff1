"""Plots through matplotlib (headless Agg): figures as images or PNG/SVG files.

Figures are built with ``matplotlib.figure.Figure`` (no pyplot state, safe in
worker processes); :func:`save_figure` writes one atomically, the format chosen
by the extension.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from ringscan.pipeline.formats.atomic import atomic_path
from ringscan.pipeline.formats.errors import FormatError

__all__ = ["PLOT_FORMATS", "new_figure", "figure_to_image", "save_figure", "error_histogram_figure",
           "residuals_figure"]

PLOT_FORMATS = (".png", ".svg")
"""File formats :func:`save_figure` writes (by extension)."""
DPI = 100


def new_figure(size: tuple[int, int] = (960, 600)):
    """An empty matplotlib figure of ``size`` (width, height) pixels."""
    import matplotlib

    matplotlib.use("Agg", force=False)
    from matplotlib.figure import Figure

    return Figure(figsize=(size[0] / DPI, size[1] / DPI), dpi=DPI, layout="constrained")


def figure_to_image(fig) -> np.ndarray:
    """A matplotlib figure as a BGR uint8 image (OpenCV's order, for write_image)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    canvas = FigureCanvasAgg(fig)
    canvas.draw()
    rgba = np.asarray(canvas.buffer_rgba())
    return np.ascontiguousarray(rgba[:, :, 2::-1])


def save_figure(fig, path: str | os.PathLike) -> Path:
    """Write a figure as PNG or SVG (by the extension), atomically.

    Raises:
        FormatError: another extension.
    """
    path = Path(path)
    ext = path.suffix.lower()
    if ext not in PLOT_FORMATS:
        raise FormatError(path, f"a plot is written as {' or '.join(PLOT_FORMATS)}, not {ext or '(none)'!r}")
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format=ext[1:], dpi=DPI)
    return path


def error_histogram_figure(distances: dict, *, title: str = "", max_mm: float | None = None,
                           size: tuple[int, int] = (960, 600)):
    """Histogram of point-to-surface distances (mm): all points filled, each view
    as a line when there are several, the median and p95 of all as dashed lines.

    Args:
        distances: {view name: (N,) distances in mm}; NaN are left out.
        max_mm: right end of the axis (default: the 99.5th percentile of all).
    """
    fig = new_figure(size)
    ax = fig.add_subplot()
    finite = {k: np.asarray(v, float)[np.isfinite(v)] for k, v in distances.items()}
    every = np.concatenate(list(finite.values())) if finite else np.zeros(0)
    if every.size == 0:
        ax.text(0.5, 0.5, "no point", ha="center", va="center", transform=ax.transAxes)
        return fig
    top = float(max_mm) if max_mm else max(float(np.quantile(every, 0.995)), 1e-6)
    bins = np.linspace(0.0, top, 61)
    w = np.full(every.size, 100.0 / every.size)
    ax.hist(np.minimum(every, top), bins=bins, weights=w, color="0.75", label=f"all ({every.size} points)")
    if len(finite) > 1:
        for name, d in finite.items():
            if d.size:
                h, _ = np.histogram(np.minimum(d, top), bins=bins)
                ax.plot(0.5 * (bins[1:] + bins[:-1]), 100.0 * h / d.size, lw=1, label=name)
    for q, ls in ((0.5, "--"), (0.95, ":")):
        v = float(np.quantile(every, q))
        ax.axvline(v, color="k", ls=ls, lw=1)
        ax.annotate(f"{'median' if q == 0.5 else 'p95'} {v:.4f} mm", (v, 1.0), xycoords=("data", "axes fraction"),
                    textcoords="offset points", xytext=(3, -12), fontsize=8)
    ax.set_xlim(0.0, top)
    ax.set_xlabel(f"distance to the truth surface, mm (the last bin holds everything beyond {top:.3g})")
    ax.set_ylabel("points, %")
    ax.grid(True, color="0.9")
    ax.legend(fontsize=8, loc="upper right", ncols=2 if len(finite) > 8 else 1)
    if title:
        ax.set_title(title)
    return fig


def residuals_figure(per_view: dict, residuals: dict, *, image_size: tuple[int, int], outliers=(), title: str = "",
                     size: tuple[int, int] = (1200, 560)):
    """A calibration's reprojection residuals: each view's RMS as a bar (views that
    spoil the fit in red), and every corner's residual as an arrow across the image
    (scaled up, the scale in the key).

    Args:
        per_view: {view name: RMS px}.
        residuals: {view name: (corners (N, 2) px, residuals (N, 2) px)}.
        image_size: (width, height) of the camera image, px.
        outliers: names of the views drawn in red.
    """
    fig = new_figure(size)
    bars, field = fig.subplots(1, 2, width_ratios=[1, 1.4])
    names = list(per_view)
    vals = [float(per_view[n]) for n in names]
    # one colour per view, the same for its bar and its arrows; the views that spoil the fit in red
    colours = ["tab:red" if n in set(outliers) else f"C{k % 10}" for k, n in enumerate(names)]
    colour_of = dict(zip(names, colours))
    bars.barh(range(len(names)), vals, color=colours)
    bars.set_yticks(range(len(names)), names, fontsize=8 if len(names) < 30 else 6)
    bars.invert_yaxis()
    if vals:
        med = float(np.median(vals))
        bars.axvline(med, color="k", ls="--", lw=1)
        bars.annotate(f"median {med:.3f} px", (med, 1.0), xycoords=("data", "axes fraction"),
                      textcoords="offset points", xytext=(3, -12), fontsize=8)
    bars.set_xlabel("RMS reprojection error per view, px")
    w, h = image_size
    every = np.concatenate([r for _, r in residuals.values()]) if residuals else np.zeros((0, 2))
    norm = np.linalg.norm(every, axis=1) if len(every) else np.zeros(0)
    typical = float(np.quantile(norm, 0.95)) if len(norm) else 1.0
    scale = 0.04 * max(w, h) / max(typical, 1e-9)  # the 95th percentile residual is drawn 4 % of the image long
    for name, (c, r) in residuals.items():
        colour = colour_of.get(name, "tab:gray")
        field.quiver(c[:, 0], c[:, 1], r[:, 0] * scale, r[:, 1] * scale, angles="xy", scale_units="xy", scale=1,
                     color=colour, width=0.002)
    field.set_xlim(0, w)
    field.set_ylim(h, 0)
    field.set_aspect("equal")
    field.set_xlabel("image x, px")
    field.set_ylabel("image y, px")
    field.set_title(f"residuals across the image, drawn x{scale:.0f} (p95 {typical:.3f} px)", fontsize=10)
    if title:
        fig.suptitle(title)
    return fig
