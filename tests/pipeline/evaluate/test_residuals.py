"""The residual map bins points by their camera pixel: the median of each pixel's
residuals, NaN where no point is; a cloud without residuals is named."""

import numpy as np
import pytest

from ringscan.pipeline.evaluate.residuals import plot_residuals, residual_map


def test_each_pixel_holds_the_median_of_its_points(tmp_path):
    f = {"u": np.array([1.2, 0.8, 1.1, 3.0, -5.0]), "v": np.array([2.1, 1.9, 2.4, 0.0, 0.0]),
         "residual": np.array([0.1, 0.3, 0.2, 0.7, 9.0])}
    m = residual_map(f, width=4, height=3, check={"kind": "epipolar", "median_px": 0.2, "p95_px": 0.5,
                                                   "samples": 4, "fits": True})
    assert m.residual[2, 1] == pytest.approx(0.2) and m.residual[0, 3] == pytest.approx(0.7)
    assert np.isnan(m.residual).sum() == 10  # the pixel outside the image is left out
    assert m.summary["points"] == 4 and m.summary["median"] == pytest.approx(0.25)
    plot_residuals(m, tmp_path / "m.png")
    assert (tmp_path / "m.png").stat().st_size > 500


def test_a_cloud_without_residuals_is_named():
    with pytest.raises(ValueError, match="no residual"):
        residual_map({"u": np.zeros(2), "v": np.zeros(2)}, width=4, height=4)
