"""Emulated devices on pseudo-terminals, so the real serial drivers can be tried
(and tested) through the real pyserial stack, and a whole virtual rig.

- :class:`EmulatedTurntable`: a GRBL 1.1 (or Horus 0.2) turntable controller:
  banner on Ctrl-X, ``ok``/``error:N`` per line, ``?`` status reports that say
  ``Run`` during a simulated move and ``Idle`` after it, alarms, ``$X``, ``G90``/
  ``G91``/``G92``/``G0``/``G1``/``G4``, ``M17``/``M18`` on Horus.
- :class:`EmulatedProjector`: a serial pattern projector (protocol in
  :mod:`ringscan.hardware.devices.projector`).
- :class:`CameraServer`: serves a camera on a Unix socket (``SocketCamera``).
- :class:`EmulatedRig`: all three around the virtual rig's renderer, as
  ``ringscan emulate`` and ``ringscan capture --virtual`` start it.

Each device runs in a background thread on the master side of a pty; the host opens
the slave path (or a stable symlink to it, like ``/dev/serial/by-id/...``). Faults
are injected with ``inject(kind, on=..., ...)``: ``error`` (refuse the line),
``silent`` (swallow it), ``alarm`` (mid-move for a motion line), ``vanish`` (the port
disappears, mid-move for a motion line), ``reset`` (the board restarts by itself).
A vanished port comes back with :meth:`replug` (a fresh pty behind the same symlink,
the controller freshly powered up, the table where the motor left it).

A rig's own temporary folder (``ringscan-emu-*``) is locked for its life (``flock``): the
folder of a rig whose process was killed (SIGKILL, an unhandled SIGTERM) is removed by the
next rig that starts.
"""

from __future__ import annotations

import contextlib
import fcntl
import logging
import os
import socket
import tempfile
import threading
from pathlib import Path

import numpy as np

from ringscan.hardware.emulators.virtual import VirtualCamera, make_virtual_rig
from ringscan.hardware.emulators.grbl import EmulatedTurntable
from ringscan.hardware.emulators.projector import EmulatedProjector
from ringscan.pipeline.codecs.render import render_frame
from ringscan.pipeline.formats.atomic import LOCK_NAME, lock_folder
from ringscan.pipeline.formats.patterns import frame_names

log = logging.getLogger(__name__)

__all__ = ["CameraServer", "EmulatedRig"]

FOLDER_PREFIX = "ringscan-emu-"


def _empty_folder(folder: Path, keep: str | None = None) -> None:
    """Remove the port links, socket and files of an emulator folder (not sub-folders)."""
    for p in folder.iterdir():
        if p.name != keep and (p.is_symlink() or p.is_file() or p.is_socket()):
            with contextlib.suppress(FileNotFoundError):
                p.unlink()


def remove_stale_folders(parent: str | os.PathLike) -> list[Path]:
    """Remove the ``ringscan-emu-*`` folders in ``parent`` whose rig's process is gone.

    Such a folder's lock file names its owner while it runs; the kernel drops the lock when
    the process ends however it ends, so a lock file that can be locked and names an owner
    is a killed rig's (a clean close removes it). Folders without a lock file (a rig still
    starting, or one made before the lock) are left alone. Returns the folders removed.
    """
    removed = []
    for folder in sorted(Path(parent).glob(FOLDER_PREFIX + "*")):
        try:
            fd = os.open(folder / LOCK_NAME, os.O_RDONLY | getattr(os, "O_CLOEXEC", 0))
        except OSError:
            continue
        try:
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except OSError:
                continue  # held: that rig is running
            if not os.pread(fd, 200, 0):
                continue  # its owner has created it and not locked it yet
            _empty_folder(folder)
            with contextlib.suppress(OSError):
                folder.rmdir()
                removed.append(folder)
        finally:
            os.close(fd)
    if removed:
        log.info("removed %d emulator folder(s) left by killed processes", len(removed))
    return removed


class CameraServer:
    """Serves a camera on a Unix socket (``GRAB`` -> ``FRAME h w dtype`` + raw bytes).

    Args:
        camera: the camera (grabs are serialised).
        path: the socket path; clients use the camera spec ``unix:PATH``.
    """

    def __init__(self, camera, path: str | os.PathLike):
        self.camera = camera
        self.path = Path(path)
        if self.path.exists() or self.path.is_symlink():
            self.path.unlink()
        self._sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        self._sock.bind(str(self.path))
        self._sock.listen(4)
        self._grab_lock = threading.Lock()
        self._closed = False
        self._thread = threading.Thread(target=self._accept, name="camera-server", daemon=True)
        self._thread.start()

    @property
    def spec(self) -> str:
        return f"unix:{self.path}"

    def _accept(self) -> None:
        while not self._closed:
            try:
                conn, _ = self._sock.accept()
            except OSError:
                return
            threading.Thread(target=self._serve, args=(conn,), daemon=True).start()

    def _serve(self, conn: socket.socket) -> None:
        with conn, conn.makefile("rb") as f:
            for line in f:
                if line.strip() != b"GRAB":
                    conn.sendall(b"ERR unknown request\n")
                    continue
                try:
                    with self._grab_lock:
                        img = np.ascontiguousarray(self.camera.grab())
                except Exception as e:
                    log.warning("camera server: grab failed: %s", e)
                    conn.sendall(f"ERR {e}".replace("\n", " ").encode("utf-8", "replace") + b"\n")
                    continue
                conn.sendall(f"FRAME {img.shape[0]} {img.shape[1]} {img.dtype.str}\n".encode() + img.tobytes())

    def close(self) -> None:
        self._closed = True
        try:
            self._sock.shutdown(socket.SHUT_RDWR)
        except OSError:
            pass
        self._sock.close()
        if self.path.exists():
            self.path.unlink()


class EmulatedRig:
    """A whole virtual rig: emulated turntable and projector on ptys, a virtual camera.

    Args:
        rig: the rig (pipeline.formats.rig.Rig) to render.
        patterns: the PatternSpec whose frames the projector holds (index = frame order).
        scene: scene name or mesh path (pipeline.simulate.scenes.make_scene), or a mesh.
        folder: where the port symlinks and the camera socket go (default: a new
            temporary folder, removed by :meth:`close`, or by the next rig if this
            process is killed).
        flavor: turntable firmware, "grbl" or "horus".
        time_scale: the turntable moves this many times faster than a real one.
        start_deg: the table's physical angle at start.
        seed: camera noise seed (see VirtualCamera).
        size_mm: scene size for make_scene.
        device: Warp device of the renderer.
        serve_camera: also serve the camera on ``folder/camera.sock``.
        virtual_rig: an already-built renderer (then rig/scene/size_mm/device are unused).
        latency_s: projector acknowledgement latency.
        steps_per_deg: the emulated table's ``$100`` (its angles are whole steps).
    """

    def __init__(self, rig, patterns, scene=None, *, folder=None, flavor: str = "grbl", time_scale: float = 1.0,
                 start_deg: float = 0.0, seed: int | None = None, size_mm: float = 80.0, device=None,
                 serve_camera: bool = False, virtual_rig=None, latency_s: float = 0.0,
                 steps_per_deg: float = 8.889):
        """Start the emulated devices (see the class docstring for the arguments).

        Size: its keyword-only arguments are the class's documented options, one per setting of the emulated
        devices (ringscan emulate's, ringscan capture --virtual's and the tests').
        """
        self._own_folder = folder is None
        self._lock = contextlib.ExitStack()
        if folder is None:
            remove_stale_folders(tempfile.gettempdir())
            self.folder = Path(tempfile.mkdtemp(prefix=FOLDER_PREFIX))
            self._lock.enter_context(lock_folder(self.folder, what="emulate"))
        else:
            self.folder = Path(folder)
            self.folder.mkdir(parents=True, exist_ok=True)
        frames = {n: render_frame(patterns, n) for n in frame_names(patterns)}
        self.turntable = self.projector = self.camera_server = None
        try:
            self.turntable = EmulatedTurntable(flavor=flavor, link_path=self.folder / "turntable",
                                               time_scale=time_scale, start_deg=start_deg,
                                               steps_per_deg=steps_per_deg)
            self.projector = EmulatedProjector(frames, link_path=self.folder / "projector", latency_s=latency_s)
            if virtual_rig is None:
                virtual_rig = make_virtual_rig(rig, scene, size_mm=size_mm, device=device)
            self.virtual_rig = virtual_rig
            self.camera = VirtualCamera(virtual_rig, self.projector, self.turntable, seed=seed)
            if serve_camera:
                self.camera_server = CameraServer(self.camera, self.folder / "camera.sock")
        except BaseException:
            self.close()
            raise

    @property
    def turntable_port(self) -> str:
        return self.turntable.port

    @property
    def projector_port(self) -> str:
        return self.projector.port

    @property
    def camera_spec(self) -> str | None:
        return None if self.camera_server is None else self.camera_server.spec

    def close(self) -> None:
        for dev in (self.camera_server, self.projector, self.turntable):
            if dev is not None:
                dev.close()
        if self._own_folder and self.folder.is_dir():
            _empty_folder(self.folder, keep=LOCK_NAME)
            self._lock.close()  # removes the lock file
            try:
                self.folder.rmdir()
            except OSError:
                pass

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
