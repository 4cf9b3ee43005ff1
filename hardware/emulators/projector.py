"""The serial pattern projector, emulated behind a pseudo-terminal (its line protocol, faults included)."""

from __future__ import annotations

import logging

from ringscan.hardware.devices.projector import IDENT, PROTOCOL_VERSION, FrameStore
from ringscan.hardware.emulators.pty_device import _PtyDevice

log = logging.getLogger(__name__)

__all__ = ["EmulatedProjector"]


class EmulatedProjector(_PtyDevice, FrameStore):
    """A serial pattern projector (``ringscan-projector/1``) holding frames in memory.

    Args:
        frames: name -> (H_p, W_p) uint8 image, in index order (or a sequence).
        link_path: a stable symlink to create for the port.
        latency_s: time between a SHOW and its OK (the display latching the frame).
        names_supported: answer ``NAME <i>`` (else ``ERR 1``, as a minimal firmware).
    """

    def __init__(self, frames, *, link_path=None, latency_s: float = 0.0, names_supported: bool = True):
        FrameStore.__init__(self, frames)
        self.latency_s = float(latency_s)
        self.names_supported = names_supported
        self._lose_reply = False
        self._buf = bytearray()
        _PtyDevice.__init__(self, name="projector", link_path=link_path)

    def _power_on(self) -> None:
        self.current_index = -1
        self._lose_reply = False
        self._buf = bytearray()

    def _on_bytes(self, data: bytes) -> None:
        for b in data:
            c = bytes([b])
            if c == b"\n":
                line = self._buf.decode("ascii", "replace").strip()
                self._buf.clear()
                if line:
                    self.lines.append(line)
                    self._line(line)
                if self._master is None:
                    return
            elif c != b"\r":
                self._buf += c

    def _reply(self, text: str, then=None) -> None:
        lost, self._lose_reply = self._lose_reply, False

        def go():
            if then is not None:
                then()
            if not lost:
                self._send(text + "\n")

        if self.latency_s > 0:
            self._schedule(self.latency_s, go)
        else:
            go()

    def _line(self, line: str) -> None:
        f = self._take_fault(line)
        if f is not None:
            if f.kind == "error":
                self._reply(f"ERR {f.code if f.code is not None else 3} display fault")
                return
            if f.kind == "silent":
                return
            if f.kind == "vanish":
                self._unplug()
                return
            if f.kind == "reset":
                self._power_on()
                return
            if f.kind == "lose_ok":
                self._lose_reply = True
        parts = line.split()
        cmd = parts[0].upper()
        n = len(self.images)
        if cmd == "HELLO" and len(parts) == 1:
            self._reply(f"{IDENT} {PROTOCOL_VERSION} {n} {self.width} {self.height}")
        elif cmd == "BLANK" and len(parts) == 1:
            self._reply("OK BLANK", then=lambda: setattr(self, "current_index", -1))
        elif cmd in ("SHOW", "NAME") and len(parts) == 2:
            try:
                i = int(parts[1])
            except ValueError:
                self._reply(f"ERR 1 bad index {parts[1]!r}")
                return
            if not 0 <= i < n:
                self._reply(f"ERR 2 index {i} out of range 0..{n - 1}")
            elif cmd == "SHOW":
                self._reply(f"OK {i}", then=lambda: setattr(self, "current_index", i))
            elif self.names_supported:
                self._reply(f"NAME {i} {self.names[i]}")
            else:
                self._reply(f"ERR 1 unknown command {cmd}")
        else:
            self._reply(f"ERR 1 unknown command {cmd}" if cmd not in ("HELLO", "BLANK", "SHOW", "NAME")
                        else f"ERR 1 bad syntax {line!r}")
