"""Cameras: OpenCV capture, folder replay, an emulator's socket.

Every camera gives grey frames: 2D uint8 or uint16 arrays (colour is converted
to grey, ITU-R 601 luma as OpenCV does). :meth:`CameraDevice.grab` first flushes
frames the driver buffered before the pattern changed, then returns a fresh one.

The virtual rig's camera (:class:`~ringscan.hardware.emulators.virtual.VirtualCamera`,
which renders with Warp) is an emulator, not a driver: no module here imports
kernels or the virtual rig (an import-linter contract checks it).
"""

from __future__ import annotations

import abc
import logging
import os
import socket
from pathlib import Path

import numpy as np

from ringscan.hardware.devices.base import Device
from ringscan.hardware.errors import CameraError
from ringscan.pipeline.formats.images import read_image
from ringscan.pipeline.formats.patterns import frame_names
from ringscan.pipeline.formats.scan import load_scan, read_view_frame

log = logging.getLogger(__name__)

__all__ = ["IMAGE_SUFFIXES", "to_grey", "CameraDevice", "OpenCVCamera", "FolderCamera", "SocketCamera", "open_camera"]

IMAGE_SUFFIXES = (".png", ".tif", ".tiff", ".bmp", ".jpg", ".jpeg")


def to_grey(img: np.ndarray, *, source: str = "camera") -> np.ndarray:
    """A frame as a 2D uint8/uint16 grey array (BGR/BGRA converted, one channel squeezed)."""
    import cv2

    img = np.asarray(img)
    if img.ndim == 3:
        if img.shape[2] == 1:
            img = img[:, :, 0]
        elif img.shape[2] == 3:
            img = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
        elif img.shape[2] == 4:
            img = cv2.cvtColor(img, cv2.COLOR_BGRA2GRAY)
    if img.ndim != 2 or img.dtype not in (np.uint8, np.uint16):
        raise CameraError(f"frame of shape {img.shape} and type {img.dtype} is not an 8/16-bit image", port=source,
                          retryable=False)
    return np.ascontiguousarray(img)


class CameraDevice(Device):
    """A camera that grabs grey frames on request."""

    source = "camera"

    def grab(self) -> np.ndarray:
        """Flush stale frames, then return a fresh (H, W) uint8/uint16 grey frame.

        Raises:
            CameraError: no frame (unplugged, end of a recording) or a bad frame.
        """
        self.flush()
        return to_grey(self._read(), source=self.source)

    @abc.abstractmethod
    def _read(self) -> np.ndarray:
        """One frame as the backend delivers it."""

    def flush(self) -> None:
        """Drop frames buffered before now (nothing to do for unbuffered cameras)."""

    def set_exposure(self, value: float) -> None:
        """Set a manual exposure (backend units); raises CameraError where unsupported."""
        raise CameraError(f"{type(self).__name__} has no exposure control", port=self.source, retryable=False)

    def set_gain(self, value: float) -> None:
        """Set the analogue gain (backend units); raises CameraError where unsupported."""
        raise CameraError(f"{type(self).__name__} has no gain control", port=self.source, retryable=False)

    def recover(self) -> None:
        """Bring the camera back after a fault (reopen)."""



class OpenCVCamera(CameraDevice):
    """A camera, stream or recording opened with ``cv2.VideoCapture``.

    Args:
        source: a device index (``0``), a stream URL (``rtsp://...``, ``http://...``)
            or a file: a video, or an image sequence such as ``frames/%03d.png``.
        backend: an OpenCV API preference (``cv2.CAP_V4L2``, ...); default any.
        flush_frames: frames grabbed and dropped before each frame returned, so that
            none exposed before the pattern changed comes back. Default: 4 for a live
            device or stream (at least the driver's buffer), 0 for files.
        width, height: ask the device for this frame size (live devices).
        exposure, gain: manual exposure and gain (see :meth:`set_exposure`).
        allow_auto_exposure: go on (with a warning) when the backend sets the
            exposure but cannot switch auto exposure off; by default that is a
            CameraError, since the camera would re-level between white and black.

    Raises:
        CameraError: the source does not open, or a manual exposure cannot be set.
    """

    def __init__(self, source: int | str | os.PathLike, *, backend: int | None = None, flush_frames: int | None = None,
                 width: int | None = None, height: int | None = None, exposure: float | None = None,
                 gain: float | None = None, allow_auto_exposure: bool = False):
        if isinstance(source, str) and source.strip().isdigit():
            source = int(source)
        self._src = source if isinstance(source, int) else os.fspath(source)
        self.source = str(self._src)
        self.live = isinstance(source, int) or "://" in self.source
        if flush_frames is None:
            flush_frames = 4 if self.live else 0
        if flush_frames < 0:
            raise ValueError(f"flush_frames must be >= 0, got {flush_frames}")
        self.flush_frames = int(flush_frames)
        self._backend = backend
        self._size = (width, height)
        self._exposure, self._gain = exposure, gain
        self.allow_auto_exposure = bool(allow_auto_exposure)
        self._cap = None
        self._open()

    def _open(self) -> None:
        import cv2

        if self._backend is None:
            cap = cv2.VideoCapture(self._src)
        else:
            cap = cv2.VideoCapture(self._src, self._backend)
        if not cap.isOpened():
            cap.release()
            hint = ("is the camera plugged in and free?" if isinstance(self._src, int)
                    else "check the path or URL (image sequences need a pattern such as frames/%03d.png)")
            raise CameraError(f"OpenCV cannot open it; {hint}", port=self.source, retryable=self.live)
        self._cap = cap
        if self.live:
            cap.set(cv2.CAP_PROP_BUFFERSIZE, 1)
            w, h = self._size
            if w:
                cap.set(cv2.CAP_PROP_FRAME_WIDTH, w)
            if h:
                cap.set(cv2.CAP_PROP_FRAME_HEIGHT, h)
        if self._exposure is not None:
            self.set_exposure(self._exposure)
        if self._gain is not None:
            self.set_gain(self._gain)
        log.info("camera: opened %s with OpenCV's %s backend", self.source, cap.getBackendName())

    def flush(self) -> None:
        for _ in range(self.flush_frames):
            if not self._cap.grab():
                break

    def _read(self) -> np.ndarray:
        if self._cap is None:
            raise CameraError("camera is closed", port=self.source, retryable=self.live)
        ok, img = self._cap.read()
        if not ok or img is None:
            why = "camera gave no frame (unplugged or busy?)" if self.live else "no more frames in the recording"
            raise CameraError(why, port=self.source, retryable=self.live)
        return img

    def set_exposure(self, value: float) -> None:
        """Manual exposure in the backend's units (V4L2: 100 us steps; others: log2 seconds).

        Auto exposure is switched off first (V4L2 value 1, older backends 0.25).

        Raises:
            CameraError: the backend has no exposure control, or it cannot switch
                auto exposure off (unless ``allow_auto_exposure``).
        """
        import cv2

        auto_off = self._cap.set(cv2.CAP_PROP_AUTO_EXPOSURE, 1) or self._cap.set(cv2.CAP_PROP_AUTO_EXPOSURE, 0.25)
        backend = self._cap.getBackendName()
        if not self._cap.set(cv2.CAP_PROP_EXPOSURE, float(value)):
            raise CameraError(f"the {backend} backend has no exposure control for this source",
                              port=self.source, retryable=False)
        if not auto_off:
            why = (f"the {backend} backend cannot switch auto exposure off for this source, so the camera may "
                   f"re-level between the white and the black frame")
            if not self.allow_auto_exposure:
                raise CameraError(f"{why}; switch it off by hand (v4l2-ctl -c auto_exposure=1 on Linux) or accept "
                                  f"it with --allow-auto-exposure", port=self.source, retryable=False)
            log.warning("camera %s: %s (accepted: --allow-auto-exposure)", self.source, why)
        self._exposure = value

    def set_gain(self, value: float) -> None:
        import cv2

        if not self._cap.set(cv2.CAP_PROP_GAIN, float(value)):
            raise CameraError(f"the {self._cap.getBackendName()} backend has no gain control for this source",
                              port=self.source, retryable=False)
        self._gain = value

    def recover(self) -> None:
        """Reopen a live camera (a recording is not reopened: it would start again)."""
        if self.live:
            self.close()
            self._open()

    def close(self) -> None:
        if self._cap is not None:
            self._cap.release()
            self._cap = None


class FolderCamera(CameraDevice):
    """Replays recorded frames in order.

    Args:
        folder: a scan folder (frames replayed view by view in the codec's frame
            order, as a capture of the same pattern set asks for them), or a folder
            of images (replayed in file-name order).

    Raises:
        FormatError: the scan folder is invalid.
        CameraError: the folder holds no images.
    """

    def __init__(self, folder: str | os.PathLike):

        folder = Path(folder)
        self.source = str(folder)
        if (folder / "scan.json").is_file():
            scan = load_scan(folder)
            names = frame_names(scan.patterns)
            # A frame is read when it is replayed (image file or packed store alike), as stored: a camera
            # gives its own bits (frame_bits of the new scan says them).
            self.paths = [(lambda v=v, n=n: read_view_frame(scan, v, n, raw=True)) for v in scan.views for n in names]
        else:
            self.paths = sorted(p for p in folder.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES) \
                if folder.is_dir() else []
        if not self.paths:
            raise CameraError("no frames to replay (not a scan folder, no images)", port=self.source, retryable=False)
        self.position = 0
        """Index of the next frame."""

    def _read(self) -> np.ndarray:

        if self.position >= len(self.paths):
            raise CameraError(f"all {len(self.paths)} recorded frames replayed", port=self.source, retryable=False)
        src = self.paths[self.position]
        img = src() if callable(src) else read_image(src)
        self.position += 1
        return img


class SocketCamera(CameraDevice):
    """A camera served on a Unix socket by ``ringscan emulate`` (its virtual camera).

    Protocol: the client sends ``GRAB\\n``; the server answers ``FRAME <h> <w> <dtype>\\n``
    and then h*w*itemsize raw bytes (row-major), or ``ERR <text>\\n``.

    Args:
        path: the socket path (camera spec ``unix:PATH``).
        timeout_s: longest wait for a frame.
    """

    def __init__(self, path: str | os.PathLike, *, timeout_s: float = 60.0):
        self.path = os.fspath(path)
        self.source = f"unix:{self.path}"
        self.timeout_s = timeout_s
        self._sock = None
        self._connect()

    def _connect(self) -> None:
        s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        s.settimeout(self.timeout_s)
        try:
            s.connect(self.path)
        except OSError as e:
            s.close()
            raise CameraError(f"cannot connect ({e.strerror or e}); is 'ringscan emulate' running?",
                              port=self.source) from None
        self._sock = s
        self._file = s.makefile("rb")

    def _read(self) -> np.ndarray:
        if self._sock is None:
            raise CameraError("not connected", port=self.source)
        try:
            self._sock.sendall(b"GRAB\n")
            header = self._file.readline().decode("ascii", "replace").split()
            if not header:
                raise CameraError("the emulator closed the connection", port=self.source)
            if header[0] == "ERR":
                raise CameraError(" ".join(header[1:]) or "emulator error", port=self.source)
            h, w, dtype = int(header[1]), int(header[2]), np.dtype(header[3])
            n = h * w * dtype.itemsize
            data = self._file.read(n)
            if len(data) != n:
                raise CameraError("frame cut short by the emulator", port=self.source)
        except (OSError, ValueError, IndexError, TypeError) as e:
            self.close()
            raise CameraError(f"bad or lost connection ({e})", port=self.source) from None
        return np.frombuffer(data, dtype).reshape(h, w).copy()

    def recover(self) -> None:
        self.close()
        self._connect()

    def close(self) -> None:
        if self._sock is not None:
            self._file.close()
            self._sock.close()
            self._sock = None


def open_camera(spec: str, *, flush_frames: int | None = None, exposure: float | None = None,
                gain: float | None = None, allow_auto_exposure: bool = False) -> CameraDevice:
    """A camera from a command-line spec.

    - ``0``, ``1``, ...: an OpenCV device index;
    - ``unix:PATH``: the virtual camera of ``ringscan emulate``;
    - ``folder:PATH`` or a folder: replay a recorded scan (or a folder of images);
    - anything else: an OpenCV URL, video file or image-sequence pattern
      (``exposure``, ``gain``, ``allow_auto_exposure``: see :class:`OpenCVCamera`).
    """
    spec = str(spec)
    if spec.startswith("unix:"):
        return SocketCamera(spec[5:])
    if spec.startswith("folder:") or Path(spec).is_dir():
        return FolderCamera(spec[7:] if spec.startswith("folder:") else spec)
    return OpenCVCamera(spec, flush_frames=flush_frames, exposure=exposure, gain=gain,
                        allow_auto_exposure=allow_auto_exposure)
