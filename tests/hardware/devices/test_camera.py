"""Cameras: the real OpenCV capture path (from image files), folder replay and the
emulator's socket camera (the virtual camera: tests/hardware/emulators)."""

import subprocess
import sys

import cv2
import numpy as np
import pytest

from ringscan.hardware.devices.camera import CameraDevice, FolderCamera, OpenCVCamera, SocketCamera, open_camera
from ringscan.hardware.emulators.rig import CameraServer
from ringscan.hardware.errors import CameraError
from ringscan.pipeline.formats.images import write_image
from ringscan.pipeline.formats.scan import Scan, View, save_scan


def _sequence(folder, n=4, colour=False):
    rng = np.random.default_rng(1)
    imgs = []
    for i in range(n):
        img = rng.integers(0, 256, (24, 32, 3) if colour else (24, 32), dtype=np.uint8)
        cv2.imwrite(str(folder / f"f{i:03d}.png"), img)
        imgs.append(img)
    return imgs


def test_opencv_image_sequence_in_order(tmp_path):
    imgs = _sequence(tmp_path)
    with OpenCVCamera(str(tmp_path / "f%03d.png")) as cam:
        assert not cam.live and cam.flush_frames == 0
        for img in imgs:
            got = cam.grab()
            assert got.dtype == np.uint8 and got.shape == (24, 32)
            np.testing.assert_array_equal(got, img)
        with pytest.raises(CameraError, match="no more frames") as ei:
            cam.grab()
        assert not ei.value.retryable


def test_opencv_colour_frames_become_grey(tmp_path):
    imgs = _sequence(tmp_path, n=2, colour=True)
    with OpenCVCamera(tmp_path / "f%03d.png") as cam:
        np.testing.assert_array_equal(cam.grab(), cv2.cvtColor(imgs[0], cv2.COLOR_BGR2GRAY))


def test_opencv_flush_drops_buffered_frames(tmp_path):
    imgs = _sequence(tmp_path, n=6)
    with OpenCVCamera(str(tmp_path / "f%03d.png"), flush_frames=2) as cam:
        np.testing.assert_array_equal(cam.grab(), imgs[2])   # 0, 1 flushed
        np.testing.assert_array_equal(cam.grab(), imgs[5])   # 3, 4 flushed


def test_opencv_errors(tmp_path):
    _sequence(tmp_path, n=1)
    with pytest.raises(CameraError, match="cannot open"):
        OpenCVCamera(str(tmp_path / "missing_%03d.png"))
    with OpenCVCamera(str(tmp_path / "f%03d.png")) as cam:
        with pytest.raises(CameraError, match="no exposure control") as ei:
            cam.set_exposure(100)
        assert not ei.value.retryable
    with pytest.raises(ValueError):
        OpenCVCamera(str(tmp_path / "f%03d.png"), flush_frames=-1)


class _Backend:
    """A stand-in for cv2.VideoCapture that answers ``set`` as a given backend does
    (a UVC camera whose driver has no auto exposure switch, say), so the driver's
    answer to it can be checked without the camera."""

    def __init__(self, accepts):
        self.accepts = accepts
        self.values = {}

    def __call__(self, *args):
        return self

    def isOpened(self):
        return True

    def set(self, prop, value):
        if prop in self.accepts:
            self.values[prop] = value
            return True
        return False

    def getBackendName(self):
        return "UVC-TEST"

    def read(self):
        return True, np.zeros((4, 4), np.uint8)

    def grab(self):
        return True

    def release(self):
        pass


def test_auto_exposure_that_cannot_be_switched_off_is_an_error(monkeypatch, caplog):
    # docs/hardware.md: a backend that cannot do it raises CameraError instead of silently ignoring it
    backend = _Backend({cv2.CAP_PROP_EXPOSURE, cv2.CAP_PROP_BUFFERSIZE})
    monkeypatch.setattr(cv2, "VideoCapture", backend)
    with pytest.raises(CameraError, match="cannot switch auto exposure off.*--allow-auto-exposure") as ei:
        OpenCVCamera(0, exposure=100)
    assert not ei.value.retryable
    with caplog.at_level("WARNING", logger="ringscan.hardware.devices.camera"):
        cam = open_camera("0", exposure=100, allow_auto_exposure=True)  # accepted, with a warning
    assert backend.values[cv2.CAP_PROP_EXPOSURE] == 100.0 and "auto exposure" in caplog.text
    cam.close()
    backend.accepts.add(cv2.CAP_PROP_AUTO_EXPOSURE)  # a backend that can: manual, no warning
    caplog.clear()
    with caplog.at_level("WARNING", logger="ringscan.hardware.devices.camera"):
        cam = OpenCVCamera(0, exposure=50)
    assert backend.values[cv2.CAP_PROP_AUTO_EXPOSURE] == 1 and not caplog.text
    cam.close()


def test_folder_camera_replays_a_scan_in_capture_order(tmp_path, rig, patterns):
    frames = []
    views = []
    k = 0
    for vi in range(2):
        rel = {}
        for n in ["white", "black", "gray_0", "gray_0_inv", "gray_1", "gray_1_inv"]:
            img = np.full((rig.camera.height, rig.camera.width), k, np.uint8)
            rel[n] = f"view_{vi:03d}/{n}.png"
            write_image(tmp_path / rel[n], img)
            frames.append(k)
            k += 1
        views.append(View(name=f"view_{vi:03d}", turntable_deg=90.0 * vi, frames=rel))
    save_scan(Scan(folder=tmp_path, rig=rig, patterns=patterns, views=tuple(views)))
    cam = open_camera(str(tmp_path))
    assert isinstance(cam, FolderCamera)
    got = [int(cam.grab()[0, 0]) for _ in frames]
    assert got == frames
    with pytest.raises(CameraError, match="all 12 recorded frames replayed"):
        cam.grab()


def test_folder_camera_replays_a_12_bit_scan_as_its_camera_gave_it(tmp_path, rig, patterns):
    """A scan with frame_bits 12 replays its stored values (0..4095), as a 12-bit camera delivers them,
    not the 16-bit values a reconstruction reads."""
    rel = {}
    for k, n in enumerate(["white", "black", "gray_0", "gray_0_inv", "gray_1", "gray_1_inv"]):
        rel[n] = f"view_000/{n}.png"
        write_image(tmp_path / rel[n], np.full((rig.camera.height, rig.camera.width), 1000 + k, np.uint16))
    save_scan(Scan(folder=tmp_path, rig=rig, patterns=patterns, views=(View("view_000", 0.0, rel),), frame_bits=12))
    cam = open_camera(str(tmp_path))
    got = [cam.grab() for _ in rel]
    assert all(g.dtype == np.uint16 for g in got) and [int(g[0, 0]) for g in got] == [1000 + k for k in range(6)]


def test_folder_camera_plain_folder_and_empty(tmp_path):
    imgs = _sequence(tmp_path, n=3)
    cam = FolderCamera(tmp_path)
    for img in imgs:
        np.testing.assert_array_equal(cam.grab(), img)
    (tmp_path / "empty").mkdir()
    with pytest.raises(CameraError, match="no frames"):
        FolderCamera(tmp_path / "empty")


class _Fixed(CameraDevice):
    def __init__(self, imgs):
        self.imgs = list(imgs)

    def _read(self):
        if not self.imgs:
            raise CameraError("empty", retryable=False)
        return self.imgs.pop(0)


def test_socket_camera_round_trip(tmp_path):
    a = np.arange(20 * 30, dtype=np.uint16).reshape(20, 30) * 50
    b = np.random.default_rng(0).integers(0, 255, (20, 30), dtype=np.uint8)
    server = CameraServer(_Fixed([a, b]), tmp_path / "cam.sock")
    try:
        cam = open_camera(server.spec)
        assert isinstance(cam, SocketCamera)
        np.testing.assert_array_equal(cam.grab(), a)
        got = cam.grab()
        assert got.dtype == np.uint8
        np.testing.assert_array_equal(got, b)
        with pytest.raises(CameraError, match="empty"):
            cam.grab()
        cam.close()
    finally:
        server.close()
    with pytest.raises(CameraError, match="ringscan emulate"):
        SocketCamera(tmp_path / "cam.sock")


def test_drivers_import_no_kernels():
    code = ("import sys, ringscan.hardware, ringscan.hardware.emulators, ringscan.tools.cmd_capture;"
            "bad = [m for m in sys.modules if m == 'warp' or m.startswith(('warp.', 'ringscan.kernels', "
            "'ringscan.pipeline.simulate'))];"
            "print(bad); sys.exit(1 if bad else 0)")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert r.returncode == 0, r.stdout + r.stderr
