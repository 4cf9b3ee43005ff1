"""A virtual screen for the display projector's tests: an Xvfb X server, read back
with mss (XGetImage: code independent of SDL, which draws the frames).

``virtual_screen()`` starts one Xvfb for the whole test session (1024x768, the
hardware tests' projector size) and points SDL at it. Tests that need it skip only
when pygame-ce, mss or Xvfb cannot be had; ``make test`` installs all three.
"""

from __future__ import annotations

import atexit
import collections
import os
import select
import shutil
import subprocess
import threading
import time

import numpy as np
import pytest

from ringscan.hardware.devices.camera import CameraDevice

SCREEN_W, SCREEN_H = 1024, 768
_XVFB: dict = {}


def virtual_screen() -> str:
    """The X display name of the session's Xvfb (started on first use); SDL's video
    subsystem is brought up on it."""
    if "display" in _XVFB:
        return _XVFB["display"]
    os.environ.setdefault("PYGAME_HIDE_SUPPORT_PROMPT", "1")
    pytest.importorskip("pygame", reason="pygame-ce is not installed (pip install -e '.[test]' installs it)")
    pytest.importorskip("mss", reason="mss is not installed (pip install -e '.[test]' installs it)")
    exe = shutil.which("Xvfb")
    if exe is None:
        pytest.skip("Xvfb is not installed (Debian package xvfb; tools/install_system_deps.sh, run by make test, "
                    "installs it)")
    r, w = os.pipe()
    proc = subprocess.Popen([exe, "-displayfd", str(w), "-screen", "0", f"{SCREEN_W}x{SCREEN_H}x24", "-nolisten",
                             "tcp", "-noreset"], pass_fds=(w,), stdout=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL)
    os.close(w)
    data = b""
    deadline = time.monotonic() + 20.0
    while not data.endswith(b"\n") and time.monotonic() < deadline:
        ready, _, _ = select.select([r], [], [], 0.5)
        if ready:
            chunk = os.read(r, 64)
            if not chunk:
                break
            data += chunk
    os.close(r)
    if not data.strip().isdigit():
        proc.kill()
        raise RuntimeError(f"Xvfb did not start (exit status {proc.poll()})")
    display = f":{int(data)}"
    atexit.register(_stop, proc)
    # SDL reads DISPLAY once, when its video subsystem starts: start it now, then put
    # the environment back so nothing else in the test session sees the virtual screen.
    from ringscan.hardware.devices.display import list_displays

    saved = {k: os.environ.get(k) for k in ("DISPLAY", "SDL_VIDEODRIVER")}
    os.environ.update(DISPLAY=display, SDL_VIDEODRIVER="x11")
    try:
        displays = list_displays()
    finally:
        for k, v in saved.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v
    assert [(d.width, d.height) for d in displays] == [(SCREEN_W, SCREEN_H)], displays
    _XVFB.update(display=display, proc=proc)
    return display


def _stop(proc) -> None:
    """Close SDL's connection to the X server, then stop the server (the other way
    round, Xlib reports a fatal IO error as the tests end)."""
    from ringscan.hardware.devices import display

    runner = display._RUNNER
    if runner is not None and runner.pygame is not None:
        runner.call(runner.pygame.display.quit)
    proc.terminate()
    proc.wait(5.0)


class ScreenReader:
    """Reads the virtual screen back (mss, one instance per thread as mss asks)."""

    def __init__(self, display: str):
        import mss

        self._sct = mss.MSS(display=display)
        self._mon = self._sct.monitors[1]

    def rgb(self) -> np.ndarray:
        """The screen as (H, W, 3) uint8 RGB."""
        bgra = np.asarray(self._sct.grab(self._mon))
        return np.ascontiguousarray(bgra[:, :, 2::-1])

    def grey(self) -> np.ndarray:
        """The screen as (H, W) uint8 (the green channel; the projector draws R = G = B)."""
        return np.ascontiguousarray(np.asarray(self._sct.grab(self._mon))[:, :, 1])

    def close(self) -> None:
        self._sct.close()


class ScreenPattern:
    """What the virtual screen shows now, as the virtual camera asks a projector for it:
    ``current_frame()`` is the screen read back, ``current_index`` the first of the
    frames that equals it exactly (-1: none, or black)."""

    def __init__(self, display: str, frames):
        self.reader = ScreenReader(display)
        self.frames = list(frames)
        self._now = None

    def current_frame(self) -> np.ndarray:
        self._now = self.reader.grey()
        return self._now

    @property
    def current_index(self) -> int:
        now = self.reader.grey() if self._now is None else self._now
        self._now = None
        return next((i for i, f in enumerate(self.frames) if np.array_equal(f, now)), -1)


class DelayedScreenCamera(CameraDevice):
    """A camera watching a projector that lags the screen: it sees the virtual screen as
    it was ``delay_s`` ago (a projector that buffers frames), through a rolling shutter
    whose last row is read ``readout_s`` after its first. A background thread samples
    the screen every ``sample_s``; a grab waits for its own readout to end, so every
    frame it returns was exposed after the grab began (as a flushed live camera's).

    Only a strip of ``strip`` screen columns around the centre is watched, every
    ``step``-th pixel: enough rows to see a frame torn between old and new.
    """

    source = "delayed-screen"

    def __init__(self, display: str, *, delay_s: float, readout_s: float = 0.0, sample_s: float = 0.002,
                 strip: int = 64, step: int = 4):
        self.display, self.delay_s, self.readout_s, self.sample_s = display, delay_s, readout_s, sample_s
        c0 = SCREEN_W // 2 - strip // 2
        self._cols = slice(c0, c0 + strip, step)
        self._rows = slice(0, SCREEN_H, step)
        self._history: collections.deque = collections.deque(maxlen=int(4.0 / sample_s))
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._ready = threading.Event()
        self._thread = threading.Thread(target=self._sample, daemon=True)
        self._thread.start()
        self._ready.wait(5.0)
        self.grabs = 0

    def _sample(self) -> None:
        reader = ScreenReader(self.display)
        try:
            while not self._stop.is_set():
                img = reader.grey()[self._rows, self._cols].copy()
                with self._lock:
                    self._history.append((time.monotonic(), img))
                self._ready.set()
                time.sleep(self.sample_s)
        finally:
            reader.close()

    def _at(self, t: float) -> np.ndarray:
        """The newest screen sample taken at or before ``t`` (the oldest if none)."""
        with self._lock:
            hist = list(self._history)
        best = hist[0][1]
        for ts, img in hist:
            if ts > t:
                break
            best = img
        return best

    def _read(self) -> np.ndarray:
        t0 = time.monotonic()
        end = t0 + self.readout_s
        while time.monotonic() < end + self.sample_s:
            time.sleep(self.sample_s / 2)
        rows = self._at(t0 - self.delay_s).shape[0]
        bands = max(1, min(rows, 16)) if self.readout_s > 0 else 1
        out = np.empty_like(self._at(t0 - self.delay_s))
        for b in range(bands):
            r0, r1 = b * rows // bands, (b + 1) * rows // bands
            t = t0 + self.readout_s * (b / bands) - self.delay_s
            out[r0:r1] = self._at(t)[r0:r1]
        self.grabs += 1
        return out

    def close(self) -> None:
        self._stop.set()
        self._thread.join(2.0)
