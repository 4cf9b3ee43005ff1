"""``ringscan calibrate light``: plane scans at two heights -> a rig with the fitted parallel light."""

import dataclasses
import math

import cv2
import numpy as np
import pytest

from ringscan.pipeline.formats.patterns import parse_patterns
from ringscan.pipeline.formats.rig import ParallelLight, default_rig, load_rig, save_rig
from ringscan.pipeline.simulate import VirtualRig
from ringscan.pipeline.simulate.scan import simulate_scan
from ringscan.pipeline.simulate.scenes import SceneMesh, make_chessboard
from ringscan.tools.cli import main

LIGHT = ParallelLight(R=cv2.Rodrigues(np.array([0.02, -0.01, math.radians(5.0)]))[0], t=np.zeros(3),
                      pixel_pitch_mm=0.15, axis_px=np.array([505.0, 390.0]), width=1024, height=768)


def tiny_rig():
    """A 160x128 camera (f = 325 px) with the default pose, and a tilted, rolled light: a quick CLI check."""
    rig = default_rig()
    cam = dataclasses.replace(rig.camera, width=160, height=128,
                              K=np.array([[325.0, 0, 79.5], [0, 325.0, 63.5], [0, 0, 1]]))
    return dataclasses.replace(rig, camera=cam, light=LIGHT)


def plate(h):
    v = np.array([[-150, -150, h], [150, -150, h], [150, 150, h], [-150, 150, h]], float)
    return SceneMesh(vertices=v, faces=np.array([[0, 1, 2], [0, 2, 3]], np.int32), name="plate")


@pytest.fixture(scope="module")
def scans(tmp_path_factory):
    out = tmp_path_factory.mktemp("cal_light")
    spec = parse_patterns({"codec": "gray-rings", "width": 1024, "height": 768, "center": [511.5, 383.5],
                           "rho0": 8.0, "pitch": 32.0, "bits": 4, "sector_bits": 5})
    for h in (0, 30):
        simulate_scan(out / f"z{h}", scene=plate(float(h)) if h else "plane", rig=tiny_rig(), patterns=spec,
                      progress=False)
    return out


def test_calibrate_light_writes_the_rig(scans, tmp_path, capsys):
    # The input rig has the default (wrong) light: the command replaces it.
    save_rig(tmp_path / "in.json", dataclasses.replace(tiny_rig(), light=default_rig().light))
    out = tmp_path / "rig.json"
    assert main(["calibrate", "light", str(scans / "z0"), str(scans / "z30"), "--heights", "0", "30",
                 "--rig", str(tmp_path / "in.json"), "--out", str(out), "--report", str(tmp_path / "r.json"),
                 "--device", "cpu"]) == 0
    text = capsys.readouterr().out
    assert "parallel light: pitch" in text and "z0/view_000 (z = 0 mm)" in text
    li = load_rig(out).light
    assert li.model == "parallel"
    assert np.abs(li.axis_px - LIGHT.axis_px).max() < 1.0          # a 160x128 camera: loose
    assert abs(li.pixel_pitch_mm / 0.15 - 1) < 0.005
    assert np.allclose(load_rig(out).camera.K, tiny_rig().camera.K)
    assert (tmp_path / "r.json").is_file()


def test_calibrate_light_bad_input(scans, tmp_path, capsys):
    out = tmp_path / "rig.json"
    assert main(["calibrate", "light", str(scans / "z0"), "--heights", "0", "30", "--out", str(out)]) == 2
    assert "one per scan" in capsys.readouterr().err
    assert main(["calibrate", "light", str(scans / "z0"), str(scans / "z0"), "--heights", "0", "1",
                 "--out", str(out)]) == 1
    assert "two or more heights" in capsys.readouterr().err
    assert main(["calibrate", "light", str(tmp_path / "nothing"), str(scans / "z0"), "--heights", "0", "30",
                 "--out", str(out)]) == 1
    assert "nothing" in capsys.readouterr().err
    assert not out.exists()


def test_calibrate_pose_updates_the_camera(tmp_path, capsys):
    """A board lying on the plane gives the camera's pose: the default rig's, up to a half turn about z."""
    truth = default_rig()
    K = np.array([[1300.0, 0, 319.5], [0, 1300.0, 255.5], [0, 0, 1]])
    truth = dataclasses.replace(truth, camera=dataclasses.replace(truth.camera, width=640, height=512, K=K))
    img = VirtualRig(truth, make_chessboard(9, 6, 12.0, thickness_mm=3.0), device="cpu").render(
        np.full((768, 1024), 255, np.uint8))
    cv2.imwrite(str(tmp_path / "board.png"), img)
    start = dataclasses.replace(truth, camera=dataclasses.replace(truth.camera, R=np.eye(3), t=np.array([0, 0, 500.0])))
    save_rig(tmp_path / "rig.json", start)
    assert main(["calibrate", "pose", str(tmp_path / "board.png"), "--board", "9x6", "--square", "12",
                 "--thickness", "3", "--rig", str(tmp_path / "rig.json")]) == 0
    assert "camera pose: centre" in capsys.readouterr().out
    cam = load_rig(tmp_path / "rig.json").camera
    assert np.allclose(cam.R[:, 2], truth.camera.R[:, 2], atol=2e-3)
    C, C_true = cam.center, truth.camera.center
    assert abs(C[2] - C_true[2]) < 1.0 and abs(np.hypot(*C[:2]) - np.hypot(*C_true[:2])) < 1.0   # one view
    cv2.imwrite(str(tmp_path / "small.png"), img[:100, :100])
    assert main(["calibrate", "pose", str(tmp_path / "small.png"), "--board", "9x6", "--square", "12",
                 "--rig", str(tmp_path / "rig.json")]) == 1
    assert "small.png" in capsys.readouterr().err


def test_a_fifo_chunk_in_a_packed_plane_scan_is_refused_without_blocking(tmp_path, capsys):
    """Before: `calibrate light` blocked forever opening a FIFO in a packed scan's store."""
    import os

    from ringscan.pipeline.formats.packing import pack_scan
    from tests.support.threads import in_thread
    from tests.support.noise_scan import noise_scan

    scan = tmp_path / "z0"
    noise_scan(scan, views=1)  # 40x30 frames of noise: the FIFO is met before anything is fitted
    pack_scan(scan)
    chunk = scan / "view_0" / "frames.zarr" / "c" / "2" / "0" / "0"
    chunk.unlink()
    os.mkfifo(chunk)
    rc = in_thread(lambda: main(["calibrate", "light", str(scan), "--heights", "0", "--out",
                                  str(tmp_path / "rig.json")]))
    if rc == "hung":
        with open(chunk, "wb"):
            pass
    err = capsys.readouterr().err.strip()
    assert rc == 1 and err == (f"ringscan calibrate light: error: {chunk}: frame chunk is a pipe (FIFO), not a regular "
                               "file (damaged store)"), (rc, err)
    assert not (tmp_path / "rig.json").exists()
