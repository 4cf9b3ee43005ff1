"""benchmarks/opencv_graycode_sample.py, the reference peer_speed is measured against: it reads a capture's
calibration as ringscan's reader does, and run as its own process (as real_capture.py times it) it decodes
what it decodes in this one."""

import json
import subprocess
import sys

import cv2
import numpy as np
import pytest

from ringscan.pipeline.calibrate.opencv_files import read_stereo_calibration
from ringscan.pipeline.formats.images import read_image
from ringscan.pipeline.simulate.opencv_graycode import render_graycode_captures
from tests.support.benchmark_scripts import ROOT, load_benchmark
from tests.support.opencv_graycode_rig import PH, PW, small_stereo_rig


@pytest.fixture(scope="module")
def capture(tmp_path_factory):
    """The virtual two-camera rig's Gray code as OpenCV's sample stores it (320x256 cameras, 128x96 projector)."""
    out = tmp_path_factory.mktemp("sample") / "r"
    render_graycode_captures(out, rig=small_stereo_rig(), scene="sphere", size_mm=50.0, progress=False, device="cpu")
    return out


def test_the_calibration_is_read_as_ringscan_reads_it(capture, tmp_path):
    """Its FileStorage reading gives ringscan's reader's numbers, for a file with R and T and for one with the
    4x4 ``RT_cam1_2_cam2`` only (OpenCV's test data)."""
    sample = load_benchmark("opencv_graycode_sample")
    path = capture / "calibrationParameters.yml"
    ours = read_stereo_calibration(path)
    got = sample.read_calibration(path)
    for k in ("cam1_K", "cam1_dist", "cam2_K", "cam2_dist", "R", "T"):
        np.testing.assert_allclose(np.ravel(got[k]), np.ravel(ours[k]), rtol=0, atol=1e-12, err_msg=k)
    fs = cv2.FileStorage(str(tmp_path / "rt.yml"), cv2.FILE_STORAGE_WRITE)
    for c in (1, 2):
        fs.write(f"cam{c}_intrinsics", ours[f"cam{c}_K"])
        fs.write(f"cam{c}_distorsion", np.asarray(ours[f"cam{c}_dist"], np.float64).reshape(1, -1))
    fs.write("RT_cam1_2_cam2", np.vstack([np.hstack([ours["R"], ours["T"].reshape(3, 1)]), [[0.0, 0.0, 0.0, 1.0]]]))
    fs.release()
    rt = sample.read_calibration(tmp_path / "rt.yml")
    np.testing.assert_allclose(rt["R"], ours["R"], atol=1e-12)
    np.testing.assert_allclose(rt["T"], ours["T"], atol=1e-12)


def test_as_its_own_process_it_decodes_what_it_decodes_here(capture):
    """The script's process (what real_capture.py times) prints its stages and the pixels with a disparity:
    the same count as the function gives in this process, and most of camera 1's lit pixels."""
    sample = load_benchmark("opencv_graycode_sample")
    times, pixels = sample.opencv_sample(capture, (PW, PH))
    assert set(times) == {"read", "rectify", "decode", "reproject"}
    done = subprocess.run([sys.executable, str(ROOT / "benchmarks" / "opencv_graycode_sample.py"), str(capture),
                           "--projector", f"{PW}x{PH}"], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    out = json.loads(done.stdout)
    assert out["pixels"] == pixels and set(out["times_s"]) == set(times)
    lit = int(np.count_nonzero(read_image(capture / "truth" / "capture_0_lit.png")))
    assert 0.6 * lit < pixels <= 1.05 * lit  # (0.89 here) rectified: a few pixels more or fewer than its own
