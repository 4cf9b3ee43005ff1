"""``ringscan demo``: README's main job, end to end, on a small version of the default rig.

The demo at full size (the default rig's 1280x1024 camera, 38 frames a view) with its accuracy
bounds is ``python benchmarks/demo_accuracy.py``: about 20 s a view on two cores, too slow here.
"""

from __future__ import annotations

import argparse
import fnmatch
import functools
import json
from pathlib import Path

import cv2
import numpy as np
import open3d as o3d
import pytest
import warp as wp

from ringscan.kernels.runtime import uncached_kernel_modules
from ringscan.pipeline.formats.scan import load_scan
from ringscan.pipeline.simulate import scenes
from ringscan.tools import cmd_demo
from ringscan.tools.cli import main
from tests.support.hardware_rig import small_rig

SMALL_CODEC = {"pitch": 12.0, "bits": 5, "sector_bits": 3}
"""Over the demo's own patterns (gray-rings with the angle code, 4 steps): rings 12 projector pixels
apart (1.8 mm, ~3 camera pixels of the small rig), 5 + 3 bits: 22 frames a view instead of 38."""


def test_demo_runs_the_whole_chain_on_a_small_rig(tmp_path, monkeypatch, capsys):
    """simulate -> reconstruct -> evaluate -> fuse -> mesh (ply, obj, stl) -> preview, with the demo's
    own code, object (the shipped Spot) and outputs, on the default rig's geometry with a 320x256
    camera (same field of view) and two views."""
    monkeypatch.setattr(cmd_demo, "simulate_scan", functools.partial(cmd_demo.simulate_scan, rig=small_rig()))
    monkeypatch.setattr(cmd_demo, "DEMO_PATTERNS", {**cmd_demo.DEMO_PATTERNS, **SMALL_CODEC})
    out = tmp_path / "demo"
    rc = main(["demo", "--views", "2", "--out", str(out), "--device", "cpu", "--no-progress"])
    assert rc == 0
    assert "done in" in capsys.readouterr().out
    scan = load_scan(out / "scan")
    assert scan.rig.camera.width == 320 and len(scan.views) == 2
    assert scan.patterns.angle_steps == 4  # the demo's angle code, kept
    # The truth mesh is the shipped Spot's, as make_scene places it (80 mm long); 1 µm: far above the
    # rounding of the truth file's coordinates (float32 at most: ~5 nm at 80 mm), far below any misplacement.
    truth = o3d.io.read_triangle_mesh(str(out / "scan" / scan.extra["truth"]["mesh"]))
    spot = scenes.make_scene(scenes.shipped_mesh()[0])
    assert len(truth.triangles) == len(spot.faces) == 23062
    np.testing.assert_allclose(np.asarray(truth.vertices).max(axis=0), spot.vertices.max(axis=0), atol=1e-3)
    # Points against the virtual rig's ground truth. A camera pixel of the small rig spans ~0.65 mm at
    # the object (f = 650 px, ~420 mm away); measured on Spot: median 0.039 mm, 0.04 % over 1 mm, coverage
    # 99.8 % (on the sphere: 0.036 mm, 0.5 %, 99 %).
    ev = json.loads((out / "evaluation.json").read_text())["all"]
    assert ev["points"] > 5000
    assert ev["median_mm"] <= 0.1 and ev["frac_over_1mm"] <= 0.02 and ev["coverage_mean"] >= 0.9
    # The mesh in every format, on the truth surface the light reached: within half a camera pixel
    # on average (measured 0.080 mm on Spot, 0.11 mm on the sphere).
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
    # With a scale bar: a round number of mm (Spot is 80 mm long: a fifth of the frame is 10-20 mm),
    # drawn in black ink in the lower left corner, below the object.
    assert rep["outputs"]["preview_scale_bar_mm"] in (5.0, 10.0, 20.0)
    corner = img[-30:, :120]
    assert (corner.max(axis=2) < 60).sum() > 50
    # The kernels this run used are in Warp's kernel cache now: a second run announces no compile.
    cold = uncached_kernel_modules("cpu")
    assert uncached_kernel_modules("cpu", cmd_demo.DEMO_KERNELS) == []
    assert cold is not None and "ringscan.kernels.raytrace" not in cold


def test_the_default_object_is_the_shipped_mesh_with_its_licence():
    """`ringscan demo` scans Spot, the mesh the package ships; its licence file ships beside it, and
    pyproject's package-data puts both in the wheel."""
    args = cmd_demo.add_parser(argparse.ArgumentParser().add_subparsers()).parse_args([])
    assert args.scene == cmd_demo.DEMO_SCENE == "spot"
    mesh, licence = scenes.shipped_mesh(args.scene)
    assert mesh.name == "spot.obj" and 300_000 < mesh.stat().st_size < 1_000_000  # small: 0.7 MB
    assert "public domain" in licence.read_text() and "Keenan Crane" in licence.read_text()
    assert scenes.make_scene("spot").name == "spot"
    try:
        import tomllib
    except ModuleNotFoundError:  # Python 3.10
        tomllib = pytest.importorskip("tomli")
    root = Path(__file__).resolve().parents[2]
    data = tomllib.loads((root / "pyproject.toml").read_text())["tool"]["setuptools"]
    patterns = data["package-data"]["ringscan.pipeline.simulate"]
    pkg_dir = root / data["package-dir"]["ringscan.pipeline"] / "simulate"
    for f in (mesh, licence):
        rel = f.resolve().relative_to(pkg_dir.resolve()).as_posix()
        assert any(fnmatch.fnmatch(rel, p) for p in patterns), rel


def test_a_cold_kernel_cache_is_announced_before_compiling(tmp_path, monkeypatch, capsys):
    """An empty Warp kernel cache (a first run): one line names the compile and its expected time;
    the check itself compiles nothing."""
    monkeypatch.setattr(wp.config, "kernel_cache_dir", str(tmp_path))
    cmd_demo._announce_kernel_compile("cpu")
    line = capsys.readouterr().out
    assert line.startswith(f"[0/4] first run: compiling {len(cmd_demo.DEMO_KERNELS)} Warp kernel module(s)")
    assert f"about {cmd_demo.COLD_COMPILE_S} s" in line
    assert str(tmp_path) in line and not any(tmp_path.iterdir())


def test_demo_rejects_no_views(tmp_path, capsys):
    assert main(["demo", "--views", "0", "--out", str(tmp_path / "d")]) == 2
    assert "--views" in capsys.readouterr().err
    assert not (tmp_path / "d").exists()
