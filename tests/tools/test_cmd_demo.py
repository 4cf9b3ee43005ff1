"""``ringscan demo``: README's main job, end to end, on one view of the default rig."""

from __future__ import annotations

import json

import cv2
import numpy as np
import open3d as o3d
import pytest

from ringscan.tools.cli import main


@pytest.mark.slow
def test_demo_writes_an_accurate_mesh_and_a_preview(tmp_path, capsys):
    out = tmp_path / "demo"
    rc = main(["demo", "--views", "1", "--out", str(out), "--device", "cpu"])
    assert rc == 0
    assert "done in" in capsys.readouterr().out
    # Points against the virtual rig's ground truth (the default rig and codec).
    ev = json.loads((out / "evaluation.json").read_text())["all"]
    assert ev["median_mm"] <= 0.03 and ev["frac_over_1mm"] <= 0.003 and ev["coverage_mean"] >= 0.9
    # The mesh in every format, on the truth surface the light reached.
    rep = json.loads((out / "model" / "fuse_report.json").read_text())
    assert rep["truth"]["mesh_to_truth_mean"] < 0.1
    for ext in ("ply", "obj", "stl"):
        m = o3d.io.read_triangle_mesh(str(out / "model" / f"mesh.{ext}"))
        assert len(m.triangles) > 1000, ext
    # The preview shows the object: a shaded blob that is neither empty nor the whole frame.
    img = cv2.imread(str(out / "model" / "preview.png"))
    assert img is not None and img.ndim == 3
    fg = np.any(img != img[0, 0], axis=2)
    assert 0.05 < fg.mean() < 0.9
    assert img[fg].std() > 10


def test_demo_rejects_no_views(tmp_path, capsys):
    assert main(["demo", "--views", "0", "--out", str(tmp_path / "d")]) == 2
    assert "--views" in capsys.readouterr().err
    assert not (tmp_path / "d").exists()
