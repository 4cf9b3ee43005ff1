"""Plots through matplotlib: the error histogram's figures, PNG/SVG files."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from ringscan.pipeline.formats.errors import FormatError
from ringscan.pipeline.preview.plots import error_histogram_figure, figure_to_image, save_figure


def test_error_histogram_marks_the_median_and_p95(tmp_path):
    rng = np.random.default_rng(0)
    d = {"view_000": np.abs(rng.normal(0, 0.01, 5000)), "view_001": np.r_[np.abs(rng.normal(0, 0.02, 3000)), np.nan]}
    fig = error_histogram_figure(d, title="t")
    ax = fig.axes[0]
    every = np.concatenate([v[np.isfinite(v)] for v in d.values()])
    vlines = sorted(float(ln.get_xdata()[0]) for ln in ax.get_lines() if len(set(ln.get_xdata())) == 1)
    assert vlines == pytest.approx(sorted([np.median(every), np.quantile(every, 0.95)]))
    # the bars hold every finite point, in percent
    assert sum(p.get_height() for p in ax.patches) == pytest.approx(100.0)
    assert [t.get_text() for t in ax.get_legend().get_texts()][1:] == ["view_000", "view_001"]
    img = figure_to_image(fig)
    assert img.shape == (600, 960, 3) and img.dtype == np.uint8
    save_figure(fig, tmp_path / "h.png")
    assert cv2.imread(str(tmp_path / "h.png")).shape == (600, 960, 3)
    save_figure(fig, tmp_path / "h.svg")
    assert "<svg" in (tmp_path / "h.svg").read_text()
    with pytest.raises(FormatError, match="PNG|.png"):
        save_figure(fig, tmp_path / "h.jpg")
    assert not (tmp_path / "h.jpg").exists()


def test_error_histogram_of_no_point():
    fig = error_histogram_figure({"v": np.array([np.nan])})
    assert [t.get_text() for t in fig.axes[0].texts] == ["no point"]
