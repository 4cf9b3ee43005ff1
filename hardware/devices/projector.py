"""Pattern projectors: serial-triggered (patterns preloaded on a controller) and in-memory.

The serial protocol (``ringscan-projector/1``, written down in docs/hardware.md):
ASCII lines ending in ``\\n`` (a ``\\r`` before it is ignored), one reply per command.

=================  ==========================================  =====================
host sends          device answers                              meaning
=================  ==========================================  =====================
``HELLO``           ``RINGSCAN-PROJECTOR 1 <count> <w> <h>``    identify: protocol 1,
                                                                frames, frame size
``NAME <i>``        ``NAME <i> <name>``                         name of frame i
``SHOW <i>``        ``OK <i>``                                  frame i is displayed
``BLANK``           ``OK BLANK``                                light off / black
(any)               ``ERR <code> <text>``                       refused (see below)
=================  ==========================================  =====================

Error codes: 1 unknown command or bad syntax, 2 index out of range, 3 display
fault. Empty lines are ignored (the host sends one first to end any partial line).
The device sends ``OK <i>`` only once frame i is on the light modulator, so after
the OK and the host's settle time the camera sees frame i. The index in the OK lets
the host drop a late acknowledgement of an earlier request; after a timeout the
host resynchronises with ``HELLO``, discarding everything before its reply.
"""

from __future__ import annotations

import abc
import logging
import time
from collections.abc import Mapping, Sequence

import numpy as np

from ringscan.hardware.devices.base import Device
from ringscan.hardware.devices.serial_link import LineLink
from ringscan.hardware.errors import ProjectorCommandError, ProjectorDisconnected, ProjectorError, ProjectorTimeout

log = logging.getLogger(__name__)

__all__ = ["ProjectorDevice", "SerialProjector", "VirtualProjector", "FrameStore", "PROTOCOL_VERSION", "IDENT"]

PROTOCOL_VERSION = 1
IDENT = "RINGSCAN-PROJECTOR"
ERROR_CODES = {1: "unknown command or bad syntax", 2: "index out of range", 3: "display fault"}


class ProjectorDevice(Device):
    """A projector showing preloaded frames by index (index i = the codec's i-th frame)."""

    @property
    @abc.abstractmethod
    def frame_count(self) -> int:
        """How many frames the device holds."""

    @abc.abstractmethod
    def show(self, index: int) -> None:
        """Display frame ``index``; return once the device confirms it is shown."""

    def blank(self) -> None:
        """Turn the light off (a black frame)."""

    def recover(self) -> None:
        """Bring the device back after a fault (reconnect, resynchronise)."""



class FrameStore:
    """Frames held in memory with the index now shown; a virtual camera reads it.

    Args:
        frames: uint8 (H_p, W_p) images, as a sequence or a name -> image mapping
            (index order = mapping order).
    """

    def __init__(self, frames: Sequence[np.ndarray] | Mapping[str, np.ndarray]):
        if isinstance(frames, Mapping):
            names, images = list(frames.keys()), list(frames.values())
        else:
            images = list(frames)
            names = [f"frame_{i}" for i in range(len(images))]
        if not images:
            raise ValueError("a projector needs at least one frame")
        shape = None
        for i, img in enumerate(images):
            img = np.asarray(img)
            if img.ndim != 2 or img.dtype != np.uint8:
                raise ValueError(f"frame {i} ({names[i]}) must be a 2D uint8 image, got {img.dtype} {img.shape}")
            if shape is None:
                shape = img.shape
            elif img.shape != shape:
                raise ValueError(f"frame {i} ({names[i]}) is {img.shape}, frame 0 is {shape}")
        self.names: list[str] = names
        self.images: list[np.ndarray] = [np.asarray(im) for im in images]
        self.height, self.width = shape
        self.current_index: int = -1
        """The frame shown now; -1 = blank."""
        self._black = np.zeros(shape, np.uint8)

    def current_frame(self) -> np.ndarray:
        """The (H_p, W_p) uint8 image shown now (black when blank)."""
        i = self.current_index
        return self._black if i < 0 else self.images[i]


class VirtualProjector(ProjectorDevice, FrameStore):
    """A projector in memory: ``show`` takes effect at once.

    Args:
        frames: the frames, as for :class:`FrameStore`.
    """

    def __init__(self, frames):
        FrameStore.__init__(self, frames)
        self.shown: list[int] = []
        """Every index shown, in order."""

    @property
    def frame_count(self) -> int:
        return len(self.images)

    def show(self, index: int) -> None:
        if not 0 <= index < len(self.images):
            raise ProjectorCommandError(f"frame index {index} out of range (0..{len(self.images) - 1})", code=2,
                                        retryable=False)
        self.current_index = int(index)
        self.shown.append(self.current_index)

    def blank(self) -> None:
        self.current_index = -1


class SerialProjector(ProjectorDevice):
    """A pattern projector whose controller holds the frames, driven over serial.

    Args:
        port: serial port or pyserial URL.
        baudrate: bits per second.
        timeout_s: longest wait for a reply.
        boot_timeout_s: longest wait for the HELLO reply when connecting (a board
            that resets when the port opens needs a moment).
        expect_names: the frame names the host will ask for, in index order; the
            device must hold as many frames, and where it answers ``NAME`` the
            names must match.
        connect: connect now (else call :meth:`connect`).

    Raises:
        ProjectorError: subclasses naming the port and the reason.
    """

    def __init__(self, port: str, *, baudrate: int = 115200, timeout_s: float = 2.0, boot_timeout_s: float = 3.0,
                 expect_names: Sequence[str] | None = None, connect: bool = True):
        if not timeout_s > 0 or not boot_timeout_s > 0:
            raise ValueError("timeout_s and boot_timeout_s must be > 0")
        self.port = str(port)
        self.timeout_s = float(timeout_s)
        self.boot_timeout_s = float(boot_timeout_s)
        self.expect_names = None if expect_names is None else list(expect_names)
        self.version: int | None = None
        self.width = self.height = 0
        self.names: list[str] | None = None
        """Frame names the device reported (None where it does not answer NAME)."""
        self._count = 0
        self._link = LineLink(self.port, baudrate=baudrate, name="projector", timeout_error=ProjectorTimeout,
                              disconnected_error=ProjectorDisconnected)
        if connect:
            self.connect()

    @property
    def frame_count(self) -> int:
        return self._count

    def connect(self) -> None:
        """Open the port, identify the device and check its frames."""
        self._link.open()
        try:
            self._link.write(b"\n")
            self.hello(timeout_s=self.boot_timeout_s)
            if self.expect_names is not None:
                self._check_names()
        except BaseException:
            self._link.close()
            raise

    def hello(self, *, timeout_s: float | None = None) -> None:
        """Send HELLO and read the identify line (resynchronises the reply stream)."""
        total = self.timeout_s if timeout_s is None else timeout_s
        deadline = time.monotonic() + total
        self._link.send_line("HELLO")
        while (remaining := deadline - time.monotonic()) > 0:
            line = self._link.read_line(remaining)
            if line is None:
                break
            parts = line.split()
            if not parts or parts[0] != IDENT:
                log.debug("projector: skipped %r while waiting for the HELLO reply", line)
                continue
            try:
                version, count, w, h = (int(p) for p in parts[1:5])
            except ValueError:
                raise ProjectorError(f"malformed identify line {line!r} (expected '{IDENT} <version> <count> "
                                     f"<width> <height>')", port=self.port, retryable=False) from None
            if version != PROTOCOL_VERSION:
                raise ProjectorError(f"device speaks protocol version {version}; this host speaks "
                                     f"{PROTOCOL_VERSION}", port=self.port, retryable=False)
            self.version, self._count, self.width, self.height = version, count, w, h
            log.info("projector: %d frames of %dx%d on %s", count, w, h, self.port)
            return
        raise ProjectorTimeout(f"no '{IDENT}' reply to HELLO within {total:g} s; is the projector controller on "
                               f"this port, at this baud rate?", port=self.port)

    def _check_names(self) -> None:
        want = self.expect_names
        if self._count != len(want):
            raise ProjectorError(f"device holds {self._count} frames, the pattern set has {len(want)} "
                                 f"({', '.join(want[:4])}{', ...' if len(want) > 4 else ''}); load the right "
                                 f"frames onto the controller", port=self.port, retryable=False)
        names = []
        for i, name in enumerate(want):
            self._link.send_line(f"NAME {i}")
            reply = self._reply(f"NAME {i}")
            parts = reply.split(maxsplit=2)
            if parts[0] == "ERR":
                code = _err_code(reply)
                if code == 1 and i == 0:
                    log.info("projector: device does not report frame names; only the count was checked")
                    return
                raise ProjectorCommandError(f"NAME {i} refused: {reply}", code=code, port=self.port)
            if len(parts) < 3 or parts[0] != "NAME" or parts[1] != str(i):
                raise ProjectorError(f"unexpected reply {reply!r} to 'NAME {i}'", port=self.port)
            names.append(parts[2].strip())
            if names[-1] != name:
                raise ProjectorError(f"frame {i} on the device is {names[-1]!r}, the pattern set expects {name!r}",
                                     port=self.port, retryable=False)
        self.names = names

    def _reply(self, what: str, *, accept=None) -> str:
        """The next reply line (skipping empty lines and lines ``accept`` rejects)."""
        deadline = time.monotonic() + self.timeout_s
        while (remaining := deadline - time.monotonic()) > 0:
            line = self._link.read_line(remaining)
            if line is None:
                break
            line = line.strip()
            if not line:
                continue
            if line.startswith("ERR") or accept is None or accept(line):
                return line
            log.debug("projector: dropped stale reply %r while waiting for %s", line, what)
        raise ProjectorTimeout(f"no reply to {what!r} within {self.timeout_s:g} s", port=self.port)

    def show(self, index: int) -> None:
        """``SHOW <i>`` and wait for ``OK <i>``.

        Raises:
            ProjectorCommandError: ``ERR <code> <text>``.
            ProjectorTimeout: no acknowledgement in time.
            ProjectorDisconnected: the port vanished.
        """
        index = int(index)
        if not 0 <= index < self._count:
            raise ProjectorCommandError(f"frame index {index} out of range (device holds {self._count})", code=2,
                                        port=self.port, retryable=False)
        for line in self._link.pending_lines():
            log.debug("projector: dropped unsolicited %r", line)
        self._link.send_line(f"SHOW {index}")
        ok = f"OK {index}"
        reply = self._reply(f"SHOW {index}", accept=lambda s: s.startswith("OK"))
        if reply.startswith("ERR"):
            code = _err_code(reply)
            raise ProjectorCommandError(f"SHOW {index} refused: {reply}", code=code, port=self.port,
                                        retryable=code != 2)
        if reply != ok:
            # A late OK for an earlier frame: the one we want follows.
            reply = self._reply(f"SHOW {index}", accept=lambda s: s == ok)
            if reply.startswith("ERR"):
                raise ProjectorCommandError(f"SHOW {index} refused: {reply}", code=_err_code(reply), port=self.port)

    def blank(self) -> None:
        """``BLANK`` and wait for ``OK BLANK``."""
        self._link.send_line("BLANK")
        reply = self._reply("BLANK", accept=lambda s: s == "OK BLANK")
        if reply.startswith("ERR"):
            raise ProjectorCommandError(f"BLANK refused: {reply}", code=_err_code(reply), port=self.port)

    def recover(self) -> None:
        """Reopen the port if it was lost, and resynchronise with HELLO."""
        if not self._link.is_open:
            self.connect()
            return
        try:
            self._link.discard_input()
            self._link.write(b"\n")
            self.hello()
        except ProjectorDisconnected:
            self.connect()

    def close(self) -> None:
        self._link.close()


def _err_code(line: str) -> int | None:
    parts = line.split()
    try:
        return int(parts[1])
    except (IndexError, ValueError):
        return None
