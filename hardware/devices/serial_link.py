"""A line-oriented serial link over pyserial, with typed errors.

Both serial drivers (turntable, projector) talk in ASCII lines. This wraps a
pyserial port (any ``serial_for_url`` address: ``/dev/ttyUSB0``, ``COM3``, a
pseudo-terminal, ``socket://host:port`` for a serial-over-network bridge) and
turns pyserial's exceptions into the driver's own timeout / disconnect errors.
"""

from __future__ import annotations

import logging
import time

import serial

try:  # pyserial lets termios errors through (tcdrain/tcflush on a vanished port)
    import termios

    _IO_ERRORS = (serial.SerialException, OSError, termios.error)
except ImportError:  # not POSIX
    _IO_ERRORS = (serial.SerialException, OSError)

log = logging.getLogger(__name__)

__all__ = ["LineLink"]


class LineLink:
    """A serial port read and written line by line.

    Args:
        port: the port name or pyserial URL.
        baudrate: bits per second.
        name: the device's name in log lines.
        timeout_error: exception class raised when a read times out.
        disconnected_error: exception class raised when the port vanishes.
        write_timeout_s: longest a write may block.
    """

    def __init__(self, port: str, *, baudrate: int, name: str, timeout_error: type, disconnected_error: type,
                 write_timeout_s: float = 2.0):
        self.port = str(port)
        self.baudrate = int(baudrate)
        self.name = name
        self._timeout_error = timeout_error
        self._disconnected_error = disconnected_error
        self._write_timeout_s = write_timeout_s
        self._ser = None
        self._buf = bytearray()

    @property
    def is_open(self) -> bool:
        return self._ser is not None

    def open(self) -> None:
        """Open the port (input buffer emptied)."""
        self.close()
        try:
            self._ser = serial.serial_for_url(self.port, baudrate=self.baudrate, timeout=0.1,
                                              write_timeout=self._write_timeout_s)
        except (*_IO_ERRORS, ValueError) as e:
            raise self._disconnected_error(f"cannot open the port ({e})", port=self.port) from None
        self._buf.clear()
        log.debug("%s: opened %s at %d baud", self.name, self.port, self.baudrate)

    def close(self) -> None:
        """Close the port; closing a closed or vanished port is fine."""
        ser, self._ser = self._ser, None
        self._buf.clear()
        if ser is not None:
            try:
                ser.close()
            except _IO_ERRORS:
                pass

    def _lost(self, e: Exception):
        self.close()
        return self._disconnected_error(f"connection lost ({e})", port=self.port)

    def write(self, data: bytes) -> None:
        """Write raw bytes (a line with its terminator, or a real-time byte)."""
        if self._ser is None:
            raise self._disconnected_error("port is not open", port=self.port)
        log.debug("%s > %r", self.name, data)
        try:
            self._ser.write(data)
            self._ser.flush()
        except serial.SerialTimeoutException:
            raise self._timeout_error(f"write of {data!r} timed out after {self._write_timeout_s:g} s",
                                      port=self.port) from None
        except _IO_ERRORS as e:
            raise self._lost(e) from None

    def send_line(self, text: str) -> None:
        """Write ``text`` followed by a newline."""
        self.write(text.encode("ascii") + b"\n")

    def read_line(self, timeout_s: float) -> str | None:
        """The next line without its terminator (``\\r`` stripped), or None after ``timeout_s``."""
        if self._ser is None:
            raise self._disconnected_error("port is not open", port=self.port)
        deadline = time.monotonic() + max(timeout_s, 0.0)
        looked = False
        while True:
            nl = self._buf.find(b"\n")
            if nl >= 0:
                raw = bytes(self._buf[:nl])
                del self._buf[:nl + 1]
                line = raw.decode("ascii", "replace").strip("\r")
                log.debug("%s < %r", self.name, line)
                return line
            remaining = deadline - time.monotonic()
            # Always look at what has arrived at least once: a host that stalled past the
            # deadline (a starved machine) must still read the reply that came meanwhile.
            if remaining <= 0 and looked:
                return None
            looked = True
            try:
                self._ser.timeout = min(max(remaining, 0.0), 0.5)
                chunk = self._ser.read(1)
                if chunk:
                    waiting = self._ser.in_waiting
                    if waiting:
                        chunk += self._ser.read(waiting)
            except _IO_ERRORS as e:
                raise self._lost(e) from None
            self._buf += chunk

    def pending_lines(self) -> list[str]:
        """Every complete line already received, without waiting."""
        out = []
        if self._ser is None:
            return out
        try:
            waiting = self._ser.in_waiting
            if waiting:
                self._ser.timeout = 0
                self._buf += self._ser.read(waiting)
        except _IO_ERRORS as e:
            raise self._lost(e) from None
        while True:
            line = self.read_line(0.0) if b"\n" in self._buf else None
            if line is None:
                return out
            out.append(line)

    def discard_input(self) -> None:
        """Drop everything received so far."""
        self._buf.clear()
        if self._ser is not None:
            try:
                self._ser.reset_input_buffer()
            except _IO_ERRORS as e:
                raise self._lost(e) from None
