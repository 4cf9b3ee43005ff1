"""``ringscan demo``: README's main job, end to end, on a small version of the default rig.

The demo at full size (the default rig's 1280x1024 camera, 38 frames a view) with its accuracy
bounds is ``python benchmarks/demo_accuracy.py``: about 20 s a view on two cores, too slow here.
"""

from __future__ import annotations

import functools
import json

import cv2
import numpy as np
import open3d as o3d

from ringscan.pipeline.formats.scan import load_scan
from ringscan.tools import cmd_demo
from ringscan.tools.cli import main
from tests.hardware.conftest import small_rig

SMALL_CODEC = {"pitch": 12.0, "bits": 5, "sector_bits": 3}
"""Over the demo's own patterns (gray-rings with the angle code, 4 steps): rings 12 projector pixels
apart (1.8 mm, ~3 camera pixels of the small rig), 5 + 3 bits: 22 frames a view instead of 38."""


def test_demo_runs_the_whole_chain_on_a_small_rig(tmp_path, monkeypatch, capsys):
    """simulate -> reconstruct -> evaluate -> fuse -> mesh (ply, obj, stl) -> preview, with the demo's
    own code and outputs, on the default rig's geometry with a 320x256 camera (same field of view)
    and two views."""
    monkeypatch.setattr(cmd_demo, "simulate_scan", functools.partial(cmd_demo.simulate_scan, rig=small_rig()))
    monkeypatch.setattr(cmd_demo, "DEMO_PATTERNS", {**cmd_demo.DEMO_PATTERNS, **SMALL_CODEC})
    out = tmp_path / "demo"
    rc = main(["demo", "--views", "2", "--out", str(out), "--device", "cpu", "--no-progress"])
    assert rc == 0
    assert "done in" in capsys.readouterr().out
    scan = load_scan(out / "scan")
    assert scan.rig.camera.width == 320 and len(scan.views) == 2
    assert scan.patterns.angle_steps == 4  # the demo's angle code, kept
    # Points against the virtual rig's ground truth. A camera pixel of the small rig spans ~0.65 mm at
    # the object (f = 650 px, ~420 mm away); measured: median 0.036 mm, 0.5 % over 1 mm, coverage 99 %.
    ev = json.loads((out / "evaluation.json").read_text())["all"]
    assert ev["points"] > 5000
    assert ev["median_mm"] <= 0.1 and ev["frac_over_1mm"] <= 0.02 and ev["coverage_mean"] >= 0.9
    # The mesh in every format, on the truth surface the light reached: within half a camera pixel
    # on average (measured 0.11 mm).
    rep = json.loads((out / "model" / "fuse_report.json").read_text())
    assert rep["truth"]["mesh_to_truth_mean"] < 0.3
    assert [v["name"] for v in rep["fusion"]["views"]] == ["view_000", "view_001"]
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
