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

__all__ = ["PLOT_FORMATS", "new_figure", "figure_to_image", "save_figure", "error_histogram_figure"]

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
