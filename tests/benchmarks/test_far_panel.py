"""benchmarks/far_panel.py's measures on points placed with known errors."""

import json

import numpy as np

from ringscan.pipeline.formats.rig import load_rig
from ringscan.pipeline.geometry import project_points
from tests.support.benchmark_scripts import load_benchmark


def _rig(tmp_path):
    fp = load_benchmark("far_panel")
    path = tmp_path / "rig.json"
    path.write_text(json.dumps(fp.far_rig()))
    return load_rig(path)


def test_the_rig_sees_the_panel_at_1_m_with_about_one_and_a_half_camera_px_a_projector_px(tmp_path):
    rig = _rig(tmp_path)
    cam = rig.camera
    center = -cam.R.T @ cam.t
    assert abs(np.linalg.norm(center) - np.hypot(1000.0, 250.0)) < 1e-6
    # two panel points a projector pixel apart (1000 mm / 1640 px) land ~1.5 camera px apart
    step = 1000.0 / 1640.0
    uv = project_points(np.array([[0.0, 0.0, 0.0], [0.0, step, 0.0]]), cam.R, cam.t, cam.K, cam.dist)
    assert abs(uv[0, 0] - 639.5) < 1.0 and abs(uv[0, 1] - 511.5) < 1.0  # aimed at the origin
    assert 1.3 < np.linalg.norm(uv[1] - uv[0]) < 1.7


def test_panel_figures_read_the_error_along_each_ray_the_zigzag_and_the_sigmas_honesty(tmp_path):
    fp = load_benchmark("far_panel")
    center = np.array([-250.0, 0.0, 1000.0])
    h, w = 40, 60
    v, u = np.mgrid[0:h, 0:w]
    X = np.stack([u.ravel() * 0.4, v.ravel() * 0.4, np.zeros(u.size)], 1)  # the panel's points, z = 0
    d = (X - center) / np.linalg.norm(X - center, axis=1)[:, None]
    rng = np.random.default_rng(1)
    e = rng.normal(0.0, 0.05, len(X))  # along each ray, mm
    sigma = np.full(len(X), 0.05)
    uv = np.stack([u.ravel(), v.ravel()], 1).astype(np.float32)
    lit = np.ones((h, w), bool)
    lit[:, :10] = False  # points there count, but not towards the lit share
    f = fp.panel_figures(X + e[:, None] * d, sigma, uv, center, lit)
    assert np.allclose(f["median"], np.median(np.abs(e)), atol=1e-9)
    # 2400 draws: the median |e|/sigma of a Gaussian (0.674) to ~3 %, the share beyond 3 sigma ~0.3 %
    assert abs(f["ratio"] - fp.GAUSS_MEDIAN_RATIO) < 0.05 and f["beyond_3"] < 0.01
    assert f["points"] == h * w and abs(f["of_lit"] - 1.0) < 1e-12

    # a misread bit's zigzag: every other column 1 mm off the plane along its ray
    zig = np.where(u.ravel() % 2 == 1, 1.0, 0.0)
    g = fp.panel_figures(X + zig[:, None] * d, sigma, uv, center, lit)
    cos = -d[:, 2]  # along the plane's normal a ray's 1 mm is cos(incidence) mm
    assert abs(g["rough_median"] - np.median(cos)) < 0.02
    assert g["beyond_3"] > 0.45  # half the points 20 sigma out
