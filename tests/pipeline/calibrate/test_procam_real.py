"""Calibration of the real procam captures (../shared/data/procam; skipped where absent).

The truth: calibration_result.xml's camera intrinsics (published with the data, and
agreeing with a fresh calibration) and OpenCV's own stereo calibration.
"""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from ringscan.pipeline.calibrate.board import Board, BoardView, detect_board
from ringscan.pipeline.calibrate.camera import CameraSettings, calibrate_camera
from ringscan.pipeline.calibrate.capture_reader import read_capture
from ringscan.pipeline.calibrate.errors import CalibrationError
from ringscan.pipeline.calibrate.opencv_files import read_opencv_calibration
from ringscan.pipeline.calibrate.procam import calibrate_procam, capture_corners
from tests.support.shared_data import need_shared

BOARD = Board(9, 7, 75.0)
PROJ = (1024, 768)


@pytest.fixture(scope="session")
def procam(shared_data):
    need_shared(shared_data / "procam" / "capture_1", "procam captures")
    return shared_data / "procam"


@pytest.fixture(scope="session")
def corners(procam):
    return [capture_corners(read_capture(procam / f"capture_{i}", projector=PROJ), board=BOARD, name=f"capture_{i}")
            for i in (1, 2, 3)]


@pytest.fixture(scope="session")
def calibration(corners):
    return calibrate_procam(corners, board=BOARD, camera_size=(1280, 1024), projector_size=PROJ)


def test_board_found_in_every_white_frame(corners):
    for c in corners:
        assert c.camera_view.found and len(c.camera_view.ids) == 63
        assert c.projector_view.found and len(c.projector_view.ids) == 63
        # projector corners lie on the projector image
        p = c.projector_view.corners
        assert p[:, 0].min() > 0 and p[:, 0].max() < 1024 and p[:, 1].min() > 0 and p[:, 1].max() < 768


def test_camera_focal_within_one_percent_of_the_published_file(calibration, procam):
    ref = read_opencv_calibration(procam / "calibration_result.xml")
    fx, fy = calibration.camera.K[0, 0], calibration.camera.K[1, 1]
    assert abs(fx / ref["cam_K"][0, 0] - 1) < 0.01
    assert abs(fy / ref["cam_K"][1, 1] - 1) < 0.01
    assert "k3" in calibration.camera.fixed and calibration.camera.dist[4] == 0


def test_stereo_reprojection_error_at_most_0_4_px(calibration):
    assert calibration.stereo_rms <= 0.4
    assert set(calibration.stereo_per_view) == {"capture_1", "capture_2", "capture_3"}
    # the projector: ~1890 px focal length, principal point below the image
    assert 1850 < calibration.projector.K[0, 0] < 1930
    assert calibration.projector.K[1, 2] > 768


def test_free_k3_runs_away_with_three_views(corners):
    views = [c.camera_view for c in corners]
    free = calibrate_camera(views, board=BOARD, size=(1280, 1024), settings=CameraSettings(fix_k3=False))
    fixed = calibrate_camera(views, board=BOARD, size=(1280, 1024))
    assert abs(free.dist[4]) > 100  # what three views cannot pin down
    assert fixed.dist[4] == 0 and abs(fixed.dist[1]) < 10


def test_published_projector_intrinsics_do_not_fit(corners, calibration, procam):
    """The file's projector K reprojects the decoded corners far worse than ours; halved it is closer."""
    ref = read_opencv_calibration(procam / "calibration_result.xml")

    def rms(K, dist):
        errs = []
        for c in corners:
            obj = np.concatenate([np.mgrid[0:9, 0:7].T.reshape(-1, 2) * 75.0, np.zeros((63, 1))], 1)
            ok, rv, tv = cv2.solvePnP(obj, c.projector_view.corners.astype(np.float64), K, dist)
            p, _ = cv2.projectPoints(obj, rv, tv, K, dist)
            errs.append(np.sum((p.reshape(-1, 2) - c.projector_view.corners) ** 2, 1))
        return float(np.sqrt(np.mean(np.concatenate(errs))))

    ours = rms(calibration.projector.K, calibration.projector.dist)
    theirs = rms(ref["proj_K"], ref["proj_dist"])
    assert ours < 0.5 < theirs


def test_no_board_is_a_clear_error(procam):
    black = cv2.imread(str(procam / "capture_1" / "graycode_41.png"), cv2.IMREAD_GRAYSCALE)
    v = detect_board(black, board=BOARD, name="black")
    assert not v.found and v.reason == "not found"
    with pytest.raises(CalibrationError, match="no image shows the 9x7 board.*black: not found"):
        calibrate_camera([v, v], board=BOARD, size=(1280, 1024))


def test_too_few_views_is_a_clear_error(corners):
    with pytest.raises(CalibrationError, match="only 2 distinct board pose"):
        calibrate_camera([c.camera_view for c in corners[:2]], board=BOARD, size=(1280, 1024))
    with pytest.raises(CalibrationError, match="projector calibration: only 2 capture"):
        bad = corners[2].__class__(corners[2].name, corners[2].camera_view, BoardView("x", False, "only 3 corners", None, None))
        calibrate_procam([corners[0], corners[1], bad], board=BOARD, camera_size=(1280, 1024), projector_size=PROJ)


def test_wrong_layout_of_a_real_capture(procam):
    with pytest.raises(CalibrationError, match="darker"):
        read_capture(procam / "capture_1", projector=PROJ, layout="opencv-graycode-wb-first")


def test_three_distinct_captures_leave_nothing_undetermined(calibration):
    # the fit's own deviations are far inside the bounds (docs/calibration.md): fx to
    # 0.4 % (camera) and 0.6 % (projector), the principal points to 2 % of the image
    assert calibration.problems == [] and calibration.duplicates == []
    assert calibration.camera.std[0] < 0.005 * calibration.camera.K[0, 0]
    assert calibration.projector.std[0] < 0.007 * calibration.projector.K[0, 0]


def test_one_capture_three_times_is_refused(corners):
    with pytest.raises(CalibrationError, match="only 1 distinct board pose.*capture_1 = capture_1"):
        calibrate_procam([corners[0]] * 3, board=BOARD, camera_size=(1280, 1024), projector_size=PROJ)


def test_capture_corners_of_folders_decodes_a_folder_given_again_once(tmp_path, monkeypatch):
    """A folder given twice (here as ``c1`` and ``c1/../c1``) is read and located once; its repeat is a copy of
    its own (calibrate_procam tells repeats apart by identity); a capture of another frame size is refused."""
    from types import SimpleNamespace

    from ringscan.pipeline.calibrate import procam
    from ringscan.pipeline.calibrate.procam import CaptureCorners, capture_corners_of_folders
    from ringscan.pipeline.formats.errors import FormatError

    for name in ("c1", "c2"):
        (tmp_path / name).mkdir()
    sizes = {"c1": (48, 64), "c2": (40, 64)}
    reads = []

    def read(folder, **kw):
        reads.append(folder)
        return SimpleNamespace(white=np.zeros(sizes[tmp_path.joinpath(folder).resolve().name]))

    def corners(cap, *, board, name, settings):
        v = BoardView(name, False, "not found", None, None)
        return CaptureCorners(name, v, v)

    monkeypatch.setattr(procam, "read_capture", read)
    monkeypatch.setattr(procam, "capture_corners", corners)
    seen = []
    folders = [str(tmp_path / "c1"), str(tmp_path / "c1" / ".." / "c1")]
    caps, size = capture_corners_of_folders(folders, board=Board(cols=9, rows=7, square=5.0), projector=(64, 48),
                                            progress=False, on_capture=seen.append)
    assert len(reads) == 1 and size == (64, 48) and [c.name for c in caps] == ["c1", "c1"]
    assert caps[0] is not caps[1] and seen == caps
    with pytest.raises(FormatError, match=r"c2: frames are 64x40, .*c1 has 64x48"):
        capture_corners_of_folders([str(tmp_path / "c1"), str(tmp_path / "c2")],
                                   board=Board(cols=9, rows=7, square=5.0), projector=(64, 48), progress=False)
