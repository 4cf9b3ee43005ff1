"""Calibration from a scan's own matches: gathering and subsampling, the two cameras' points, the rig file
given in place of the scan's (pipeline/calibrate/scan_matches). The commands over them: tests/tools/
test_cmd_calibrate_stereo.py."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from ringscan.pipeline.calibrate.scan_matches import gather_matches, load_scan_with_rig, two_camera_points
from ringscan.pipeline.formats.errors import FormatError
from tests.support.stereo_truth import oblique_devices, observe


def _views(n, *, two=True):
    return [SimpleNamespace(name=f"view_{k}", camera2=object() if two else None) for k in range(n)]


def test_gather_matches_subsamples_each_view_to_its_share_and_reports_it():
    scan = SimpleNamespace(path="SCAN")
    rng = np.random.default_rng(0)
    per_view = {}

    def match_view(s, v):
        n = 500 if v.name == "view_0" else 80
        u = rng.uniform(0, 100, (n, 2))
        per_view[v.name] = u
        return u, u + 1, u + 2, np.ones((n, 5))

    seen = []
    uv1, uv2, proj, sig = gather_matches(scan, _views(2), need="cameras", max_matches=400, match_view=match_view,
                                         progress=False, on_view=lambda name, n: seen.append((name, n)))
    assert seen == [("view_0", 200), ("view_1", 80)]  # 400 // 2 views: view_0 subsampled, view_1 whole
    assert uv1.shape == (280, 2) and sig.shape == (280, 5)
    assert np.array_equal(uv2, uv1 + 1) and np.array_equal(proj, uv1 + 2)
    first = per_view["view_0"]
    pick = np.sort(np.random.default_rng(0).choice(500, 200, replace=False))  # seeded by the view's index
    assert np.array_equal(uv1[:200], first[pick]) and np.array_equal(uv1[200:], per_view["view_1"])


def test_gather_matches_for_cameras_refuses_a_one_camera_view():
    views = _views(1) + _views(1, two=False)
    with pytest.raises(FormatError, match="SCAN: view view_0 has one camera's frames; matching cameras needs both"):
        gather_matches(SimpleNamespace(path="SCAN"), views, need="cameras", max_matches=1000,
                       match_view=lambda s, v: None, progress=False)


def test_two_camera_points_are_the_surface_points():
    cam1, cam2, _ = oblique_devices()
    X, u1, u2, _ = observe(2000, noise_px=0.0, seed=3)
    Xw, keep, err = two_camera_points(cam1, cam2, u1, u2)
    assert keep.all() and err.shape == (len(u1),) and float(np.max(err)) < 1e-3
    assert np.abs(Xw - X).max() < 1e-3


def test_an_opencv_file_is_refused_as_the_rig_before_the_scan_is_read(tmp_path):
    with pytest.raises(FormatError, match=r"stereo\.yml: an OpenCV FileStorage file; --rig takes a ringscan rig"):
        load_scan_with_rig(tmp_path / "no_scan", rig_path=str(tmp_path / "stereo.yml"))
