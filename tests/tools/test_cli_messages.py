"""Messages a user reads on the way (issue 35, "Other"): where the docs are for an installed ringscan,
what Ctrl-C left and whether a rerun resumes, how to get the packages URLs need, and the wait
`--watertight` brings, said before it starts."""

from __future__ import annotations

import importlib.metadata
import re
import sys

import numpy as np
import pytest

from ringscan.tools.cli import build_parser, interrupted_line, main


def test_help_points_at_docs_an_installed_ringscan_has(capsys):
    """`ringscan --help` gives the conventions themselves; the README it names is in the installed package's
    metadata (what the command it quotes prints), and every docs/ path is said to be in the source tree."""
    with pytest.raises(SystemExit):
        build_parser().parse_args(["--help"])
    text = " ".join(capsys.readouterr().out.split())
    for convention in ("-v more log", "-q errors only", "--no-progress", "130 interrupted", "2 usage error"):
        assert convention in text, convention
    for m in re.finditer(r"docs/\S*", text):  # each cited doc path: "in ringscan's source tree" right after
        assert "in ringscan's source tree" in text[m.start() - 40:m.end() + 40], text
    readme = importlib.metadata.metadata("ringscan").get_payload()
    assert readme.startswith("# ringscan") and "## Quick start" in readme
    assert "m.metadata('ringscan').get_payload()" in text


@pytest.mark.parametrize("command, hint", [
    ("reconstruct", "--resume keeps the views already done"),
    ("batch", "resumes: finished scans are skipped"),
    ("capture", "--resume` continues the capture"),
    ("fuse", "a rerun starts over"),
])
def test_interrupted_says_whether_a_rerun_resumes(command, hint):
    line = interrupted_line(command)
    assert line.startswith(f"ringscan {command}: interrupted; what was written so far is whole") and hint in line


def test_interrupted_reconstruct_from_the_command_line(tmp_path, capsys, monkeypatch):
    from ringscan.tools import cmd_reconstruct

    def interrupted(args):
        raise KeyboardInterrupt

    monkeypatch.setattr(cmd_reconstruct, "run", interrupted)
    assert main(["reconstruct", str(tmp_path), "--out", str(tmp_path / "r")]) == 130
    assert "--resume keeps the views already done" in capsys.readouterr().err


def test_url_without_fsspec_names_packages_that_install(monkeypatch):
    """ringscan is not on a package index: the hint names fsspec and s3fs, or the source tree's extra."""
    from ringscan.pipeline.formats import storage
    from ringscan.pipeline.formats.errors import RingscanError

    monkeypatch.setitem(sys.modules, "fsspec", None)  # import fsspec -> ImportError
    monkeypatch.setattr(storage, "_filesystems", {})
    with pytest.raises(RingscanError) as e:
        storage.filesystem("s3://bucket/scans")
    msg = str(e.value)
    assert "pip install fsspec s3fs" in msg and "'.[cloud]' in ringscan's source tree" in msg
    assert "ringscan[cloud]" not in msg


def test_watertight_is_announced_before_the_wait(tmp_path, capsys, monkeypatch):
    """`ringscan mesh --watertight` says the wait first (printed before meshing starts), and --help says it."""
    import open3d as o3d

    from ringscan.tools import cmd_mesh

    rng = np.random.default_rng(0)
    p = rng.normal(size=(3000, 3))
    p = 20.0 * p / np.linalg.norm(p, axis=1, keepdims=True)  # a 20 mm sphere's surface
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(p))
    cloud.normals = o3d.utility.Vector3dVector(p / 20.0)
    o3d.io.write_point_cloud(str(tmp_path / "c.ply"), cloud)
    said = []
    real = cmd_mesh.mesh_cloud

    def meshing(*a, **k):  # what had been printed when meshing began
        said.append(capsys.readouterr().out)
        return real(*a, **k)

    monkeypatch.setattr(cmd_mesh, "mesh_cloud", meshing)
    assert main(["mesh", str(tmp_path / "c.ply"), "--out", str(tmp_path / "m.ply"), "--watertight",
                 "--poisson-depth", "6", "--no-progress"]) == 0
    assert said and "--watertight: closing the surface where no view looked takes several times" in said[0]
    with pytest.raises(SystemExit):
        build_parser("mesh").parse_args(["mesh", "--help"])
    assert "several times an open mesh's time" in " ".join(capsys.readouterr().out.split())


def test_projector_from_scan_on_a_parallel_light_says_what_it_is(tmp_path, monkeypatch, capsys):
    """A two-camera scan under a collimated light (the virtual rig's default): no pinhole projector fits, and
    the error says why in ringscan's words, not OpenCV's "Principal point must be within the image"."""
    from ringscan.pipeline.formats.rig import Rig, UncalibratedLight
    from ringscan.tools import cmd_calibrate_scan
    from tests.support.decoded_scan import VOLUME, write_decoded_scan
    from tests.support.stereo_truth import oblique_devices, observe

    cam1, cam2, _ = oblique_devices()
    write_decoded_scan(tmp_path, Rig(camera=cam1, camera2=cam2, light=UncalibratedLight(width=1280, height=800),
                                     volume=VOLUME))
    X, u1, u2, _ = observe(20000, noise_px=0.1, seed=5)
    c, extent = X[:, :2].mean(0), np.ptp(X[:, :2], axis=0)
    parallel = (X[:, :2] - c) / (extent / [1200, 760]) + [640, 400]  # light along z: pixels affine in x, y
    monkeypatch.setattr(cmd_calibrate_scan, "view_matches", lambda scan, view, *, device, ring_curvature:
                        (u1, u2, parallel, None))
    assert main(["calibrate", "projector-from-scan", str(tmp_path), "--out", str(tmp_path / "p.json"),
                 "--no-progress"]) == 1
    err = capsys.readouterr().err.strip()
    assert "Principal point" not in err and len(err.splitlines()) == 1
    assert "an affine function of the points" in err and "parallel (collimated) light" in err
    assert "ringscan calibrate light" in err and not (tmp_path / "p.json").exists()
