"""``ringscan calibrate turntable``: a simulated scan of the chessboard scene -> a rig with the axis."""

import dataclasses
import math

import numpy as np
import pytest

from ringscan.pipeline.calibrate.turntable import axis_distance
from ringscan.pipeline.formats.patterns import parse_patterns
from ringscan.pipeline.formats.rig import Turntable, default_rig, load_rig, save_rig
from ringscan.pipeline.simulate.scan import simulate_scan
from ringscan.tools.cli import main

TT = Turntable(axis_point=np.array([-2.0, 1.0, 0.0]),
               axis_dir=np.array([0.0, math.sin(math.radians(1.0)), math.cos(math.radians(1.0))]))


def rig(turntable=TT):
    r = default_rig()
    K = np.array([[1300.0, 0, 319.5], [0, 1300.0, 255.5], [0, 0, 1]])
    return dataclasses.replace(r, camera=dataclasses.replace(r.camera, width=640, height=512, K=K),
                               turntable=turntable)


@pytest.fixture(scope="module")
def board_scan(tmp_path_factory):
    spec = parse_patterns({"codec": "gray-rings", "width": 1024, "height": 768, "center": [511.5, 383.5],
                           "rho0": 8.0, "pitch": 256.0, "bits": 1, "sector_bits": 0})   # 4 frames, white among them
    out = tmp_path_factory.mktemp("cal_tt") / "board"
    simulate_scan(out, scene="chessboard", rig=rig(), patterns=spec, views=6, progress=False)
    return out


def test_calibrate_turntable_from_a_scan(board_scan, tmp_path, capsys):
    # The rig given has the default (wrong) axis: the command replaces it.
    save_rig(tmp_path / "in.json", rig(default_rig().turntable))
    out = tmp_path / "rig.json"
    assert main(["calibrate", "turntable", str(board_scan), "--board", "9x6", "--square", str(80 / 12),
                 "--rig", str(tmp_path / "in.json"), "--out", str(out), "--report", str(tmp_path / "r.json")]) == 0
    text = capsys.readouterr().out
    assert "found in 6 of 6 views" in text and "turntable axis: through" in text
    ang, dist = axis_distance(TT, load_rig(out).turntable)
    assert ang < 0.2 and dist < 0.2, (ang, dist)
    assert (tmp_path / "r.json").is_file()


def test_calibrate_turntable_from_images(board_scan, tmp_path, capsys):
    images = [str(board_scan / f"view_00{k}" / "white.png") for k in range(6)]
    save_rig(tmp_path / "in.json", rig(None))
    out = tmp_path / "rig.json"
    assert main(["calibrate", "turntable", *images, "--angles", "0", "60", "120", "180", "240", "300",
                 "--board", "9x6", "--square", str(80 / 12), "--rig", str(tmp_path / "in.json"),
                 "--out", str(out)]) == 0
    ang, dist = axis_distance(TT, load_rig(out).turntable)
    assert ang < 0.2 and dist < 0.2, (ang, dist)


def test_calibrate_turntable_bad_input(board_scan, tmp_path, capsys):
    out = tmp_path / "rig.json"
    # The wrong board (more corners than it has): found in no view.
    assert main(["calibrate", "turntable", str(board_scan), "--board", "11x8", "--square", "8",
                 "--out", str(out)]) == 1
    assert "found in 0 of 6 views" in capsys.readouterr().err
    image = str(board_scan / "view_000" / "white.png")
    assert main(["calibrate", "turntable", image, image, "--angles", "0", "--board", "9x6", "--square", "8",
                 "--out", str(out)]) == 2
    assert "one per image" in capsys.readouterr().err
    assert main(["calibrate", "turntable", image, "--angles", "0", "--board", "9x6", "--square", "8",
                 "--out", str(out)]) == 2
    assert "--rig" in capsys.readouterr().err
    assert main(["calibrate", "turntable", str(board_scan), "--frame", "gray_3", "--board", "9x6", "--square", "8",
                 "--out", str(out)]) == 1
    assert "no 'gray_3' frame" in capsys.readouterr().err
    assert not out.exists()


def test_a_tenfold_square_is_refused_unless_forced(board_scan, tmp_path, capsys):
    # --square 10x the real one puts every board pose 10x farther from the camera:
    # the fit is as good as ever (the same image geometry), the axis lands far outside
    # the working volume.
    save_rig(tmp_path / "in.json", rig(default_rig().turntable))
    out = tmp_path / "rig.json"
    argv = ["calibrate", "turntable", str(board_scan), "--board", "9x6", "--square", str(800 / 12),
            "--rig", str(tmp_path / "in.json"), "--out", str(out)]
    assert main(argv) == 1
    err = capsys.readouterr().err
    assert "far outside the rig's working volume" in err and "--force" in err and len(err.strip().splitlines()) == 1
    assert not out.exists()
    assert main(argv + ["--force"]) == 0
    assert "warning: the board is seen" in capsys.readouterr().out and out.is_file()


def test_images_of_another_size_than_the_rig_are_refused(board_scan, tmp_path, capsys):
    small = rig(None)
    small = dataclasses.replace(small, camera=dataclasses.replace(small.camera, width=320, height=256))
    save_rig(tmp_path / "in.json", small)
    images = [str(board_scan / f"view_00{k}" / "white.png") for k in range(3)]
    out = tmp_path / "rig.json"
    assert main(["calibrate", "turntable", *images, "--angles", "0", "60", "120", "--board", "9x6",
                 "--square", str(80 / 12), "--rig", str(tmp_path / "in.json"), "--out", str(out)]) == 1
    assert "image is 640x512, the camera of" in capsys.readouterr().err and not out.exists()
    # a scan whose frames are not the rig's size likewise
    assert main(["calibrate", "turntable", str(board_scan), "--board", "9x6", "--square", str(80 / 12),
                 "--rig", str(tmp_path / "in.json"), "--out", str(out)]) == 1
    assert "the scan's frames are 640x512" in capsys.readouterr().err and not out.exists()
