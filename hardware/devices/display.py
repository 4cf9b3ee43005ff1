"""The display projector: pattern frames full-screen on a second display.

Most structured-light rigs drive an ordinary HDMI/DLP projector as a second screen
of the computer. :class:`DisplayProjector` opens one borderless full-screen window
on the chosen display (by index or name, :func:`list_displays`) and shows each
frame pixel for pixel: a W x H frame on a W x H display at 1:1, no scaling, no
smoothing (a size mismatch is an error unless ``centre`` is asked for). ``show``
returns once the frame has been presented with vsync, plus ``latency_s``: the time
the projector itself needs before the camera sees the frame in full, measured by
``ringscan calibrate latency`` (hardware/capture/latency.py) and kept in the rig
file.

The window is drawn with SDL through pygame-ce, the optional extra
``ringscan[display]`` (docs/hardware.md says why); pygame is imported on first use,
so importing ringscan.hardware never loads it. Every SDL call runs on one thread of
its own, which also handles the window's events between frames, so the desktop
never marks the window as not responding during a long turntable move. On macOS,
where windows belong to the main thread, the calls run on the caller's thread and
events are handled at each call.
"""

from __future__ import annotations

import collections
import ctypes
import ctypes.util
import glob
import logging
import math
import os
import queue
import sys
import threading
import time
from collections.abc import Callable
from concurrent.futures import Future
from dataclasses import dataclass

import numpy as np

from ringscan.hardware.devices.projector import FrameStore, ProjectorDevice
from ringscan.hardware.errors import ProjectorCommandError, ProjectorError

log = logging.getLogger(__name__)

__all__ = ["DEFAULT_REFRESH_HZ", "DisplayInfo", "DisplayProjector", "list_displays", "choose_display", "run_viewer",
           "VIEWER_KEYS", "parse_display_spec"]

DEFAULT_REFRESH_HZ = 60.0
"""Refresh rate assumed where the display does not report one."""
INSTALL_HINT = "pip install pygame-ce (or '.[display]' in ringscan's source tree)"
PUMP_INTERVAL_S = 0.05
"""Longest time the SDL thread leaves the window's events unhandled."""
_WINDOWPOS_CENTERED_DISPLAY = 0x2FFF0000  # SDL_WINDOWPOS_CENTERED_DISPLAY(i) = this | i

VIEWER_KEYS = {
    "right": "next", "space": "next", "page down": "next", "down": "next", "return": "next",
    "left": "previous", "backspace": "previous", "page up": "previous", "up": "previous",
    "home": "first", "end": "last", "b": "blank", "q": "quit", "escape": "quit",
}
"""Keys of :func:`run_viewer` (pygame key names) and what they do."""


@dataclass(frozen=True)
class DisplayInfo:
    """One display (monitor or projector) as the windowing system reports it."""

    index: int
    """SDL's display index (0 = the primary display, as a rule)."""
    name: str
    """The display's name (the monitor's own name, or the output's: ``HDMI-1``)."""
    x: int
    """Left edge on the desktop (screen coordinates)."""
    y: int
    """Top edge on the desktop (screen coordinates)."""
    width: int
    """Width of the desktop mode in pixels."""
    height: int
    """Height of the desktop mode in pixels."""
    refresh_hz: float
    """Refresh rate of the desktop mode (0 = not reported)."""

    def describe(self) -> str:
        rate = f", {self.refresh_hz:g} Hz" if self.refresh_hz else ""
        return f"{self.index}: {self.name!r} {self.width}x{self.height} at ({self.x}, {self.y}){rate}"


def choose_display(displays: list[DisplayInfo], spec: int | str) -> DisplayInfo:
    """The display that ``spec`` names: an index (``1``, ``"1"``) or a name (the whole
    name, any case, else a part of it that only one display's name contains).

    Raises:
        ProjectorError: no such display, or several match; the message lists them all.
    """
    listing = "; ".join(d.describe() for d in displays) or "none"
    if isinstance(spec, bool):
        raise ValueError(f"display must be an index or a name, got {spec!r}")
    if isinstance(spec, (int, np.integer)) or (isinstance(spec, str) and spec.strip().isdigit()):
        i = int(spec)
        if 0 <= i < len(displays):
            return displays[i]
        raise ProjectorError(f"there is no display {i}; the displays are: {listing}", port="display",
                             retryable=False)
    name = str(spec).strip().lower()
    exact = [d for d in displays if d.name.lower() == name]
    if len(exact) == 1:
        return exact[0]
    part = exact or [d for d in displays if name in d.name.lower()]
    if len(part) == 1:
        return part[0]
    what = "several displays match" if part else "no display is called"
    raise ProjectorError(f"{what} {spec!r}; the displays are: {listing}", port="display", retryable=False)


def parse_display_spec(spec: str) -> int | str | None:
    """The display a ``--projector`` value names: ``display`` (display 0), ``display:N``
    (an index) or ``display:NAME``; None for anything else (a serial port)."""
    s = str(spec).strip()
    if s == "display":
        return 0
    if not s.startswith("display:"):
        return None
    rest = s[len("display:"):].strip()
    if not rest:
        raise ValueError(f"--projector {spec!r}: name the display after 'display:' (an index such as 1, or a name)")
    return int(rest) if rest.isdigit() else rest


# ----------------------------------------------------------------------------- the SDL thread


def _import_pygame():
    """pygame-ce and its SDL video module, loaded on first use."""
    os.environ.setdefault("PYGAME_HIDE_SUPPORT_PROMPT", "1")
    os.environ.setdefault("SDL_NO_SIGNAL_HANDLERS", "1")  # Ctrl-C stays a KeyboardInterrupt
    os.environ.setdefault("SDL_WINDOWS_DPI_AWARENESS", "permonitorv2")  # Windows: real pixels, no bitmap scaling
    try:
        import pygame
        from pygame._sdl2 import video
    except ImportError as e:
        raise ProjectorError(f"the display projector needs pygame-ce ({e}); install it with {INSTALL_HINT}",
                             port="display", retryable=False) from None
    if not getattr(pygame, "IS_CE", False):
        raise ProjectorError("the display projector needs pygame-ce, but the original pygame is installed under the "
                             "same name; run 'pip uninstall pygame' and then " + INSTALL_HINT, port="display",
                             retryable=False)
    return pygame, video


class _Rect(ctypes.Structure):
    _fields_ = [("x", ctypes.c_int), ("y", ctypes.c_int), ("w", ctypes.c_int), ("h", ctypes.c_int)]


def _sdl_library(pygame):
    """The SDL2 library pygame loaded (for display names and positions, which pygame
    does not expose), or None."""
    here = os.path.dirname(pygame.__file__)
    paths = sorted(glob.glob(os.path.join(here, "..", "pygame_ce.libs", "libSDL2-2*"))) \
        + sorted(glob.glob(os.path.join(here, ".dylibs", "libSDL2-2*"))) + sorted(glob.glob(os.path.join(here, "SDL2.dll")))
    found = ctypes.util.find_library("SDL2")
    for path in paths + ([found] if found else []):
        try:
            lib = ctypes.CDLL(path)
            lib.SDL_GetDisplayName.restype = ctypes.c_char_p
            lib.SDL_GetDisplayName.argtypes = [ctypes.c_int]
            lib.SDL_GetDisplayBounds.argtypes = [ctypes.c_int, ctypes.POINTER(_Rect)]
            return lib
        except (OSError, AttributeError):
            continue
    return None


class _SdlThread:
    """Runs every SDL call on one thread (or inline, on macOS) and hands the window
    events to the listeners between calls."""

    def __init__(self, threaded: bool):
        self.pygame = self.video = None
        self._lib = False
        self._listeners: list[Callable] = []
        self._jobs: queue.Queue = queue.Queue()
        self._thread = None
        if threaded:
            self._thread = threading.Thread(target=self._loop, name="ringscan-sdl", daemon=True)
            self._thread.start()

    def call(self, fn: Callable, *args):
        """``fn(*args)`` on the SDL thread; its result, or its exception raised here."""
        if self._thread is None or threading.current_thread() is self._thread:
            try:
                return fn(*args)
            finally:
                self.pump()
        fut: Future = Future()
        self._jobs.put((fn, args, fut))
        return fut.result()

    def _loop(self) -> None:
        while True:
            try:
                fn, args, fut = self._jobs.get(timeout=PUMP_INTERVAL_S)
            except queue.Empty:
                self.pump()
                continue
            try:
                fut.set_result(fn(*args))
            except BaseException as e:  # handed to the caller
                fut.set_exception(e)
            self.pump()

    def pump(self) -> None:
        """Handle the window events (the desktop's is-alive pings, keys, close)."""
        pg = self.pygame
        if pg is None or not pg.display.get_init():
            return
        try:
            events = pg.event.get()
        except pg.error:
            return
        for ev in events:
            for fn in list(self._listeners):
                fn(ev)

    def listen(self, fn: Callable) -> None:
        self._listeners.append(fn)

    def unlisten(self, fn: Callable) -> None:
        if fn in self._listeners:
            self._listeners.remove(fn)

    def init_video(self):
        """pygame with its video subsystem up (on the SDL thread)."""
        if self.pygame is None:
            self.pygame, self.video = _import_pygame()
        pg = self.pygame
        if not pg.display.get_init():
            try:
                pg.display.init()
            except pg.error as e:
                hint = (f" (DISPLAY={os.environ['DISPLAY']!r})" if os.environ.get("DISPLAY")
                        else " (no DISPLAY or WAYLAND_DISPLAY: is a desktop session running?)")
                raise ProjectorError(f"no display to show patterns on: SDL says {e}{hint}", port="display",
                                     retryable=False) from None
            log.info("display: SDL video driver %s", pg.display.get_driver())
        return pg

    def displays(self) -> list[DisplayInfo]:
        pg = self.init_video()
        if self._lib is False:
            self._lib = _sdl_library(pg)
        sizes = pg.display.get_desktop_sizes()
        rates = list(pg.display.get_desktop_refresh_rates())
        out = []
        for i, (w, h) in enumerate(sizes):
            name, x, y = f"display {i}", 0, 0
            if self._lib is not None:
                raw = self._lib.SDL_GetDisplayName(i)
                if raw:
                    name = raw.decode("utf-8", "replace")
                r = _Rect()
                if self._lib.SDL_GetDisplayBounds(i, ctypes.byref(r)) == 0:
                    x, y = r.x, r.y
            rate = float(rates[i]) if i < len(rates) and rates[i] else 0.0
            out.append(DisplayInfo(index=i, name=name, x=x, y=y, width=int(w), height=int(h), refresh_hz=rate))
        return out


_RUNNER: _SdlThread | None = None
_RUNNER_LOCK = threading.Lock()


def _runner() -> _SdlThread:
    global _RUNNER
    with _RUNNER_LOCK:
        if _RUNNER is None:
            _RUNNER = _SdlThread(threaded=sys.platform != "darwin")
        return _RUNNER


def list_displays() -> list[DisplayInfo]:
    """The displays of this desktop, in SDL's order (index 0 first).

    Raises:
        ProjectorError: pygame-ce is not installed, or there is no desktop to open.
    """
    r = _runner()
    return r.call(r.displays)


# ----------------------------------------------------------------------------- the projector


@dataclass
class _Screen:
    window: object
    renderer: object
    texture: object
    rect: object


class DisplayProjector(ProjectorDevice, FrameStore):
    """Pattern frames full-screen on a display (a projector plugged in as a second screen).

    Args:
        frames: uint8 (H, W) frames, as for :class:`FrameStore` (index order = the codec's
            frame order).
        display: the display: its index (0, 1, ...) or name (see :func:`list_displays`).
        centre: frames smaller than the display are shown centred on black; without
            it a frame whose size is not the display's is refused.
        latency_s: wait after each buffer swap before ``show`` returns: the projector's
            own delay until the camera sees the frame in full (``ringscan calibrate
            latency`` measures it; the rig file keeps it as ``light.latency_s``).
        vsync: present in step with the display's refresh (keep it on: without it a
            camera may see half of one frame and half of the next).
        open: open the window now (else call :meth:`open`).
        title: the window's title (task bars and window lists show it).

    Raises:
        ProjectorError: pygame-ce missing, no desktop, no such display, a frame size that
            does not fit the display, a display that the OS scales.
    """

    def __init__(self, frames, *, display: int | str = 0, centre: bool = False, latency_s: float = 0.0,
                 vsync: bool = True, open: bool = True, title: str = "ringscan projector"):
        FrameStore.__init__(self, frames)
        if isinstance(latency_s, bool) or not isinstance(latency_s, (int, float)) or not math.isfinite(latency_s) \
                or latency_s < 0:
            raise ValueError(f"latency_s must be a finite number >= 0, got {latency_s!r}")
        self.display_spec = display
        self.centre = bool(centre)
        self.latency_s = float(latency_s)
        self.vsync = bool(vsync)
        self.title = str(title)
        self.display: DisplayInfo | None = None
        """The display the window is on (once open)."""
        self.frame_period_s = 1.0 / DEFAULT_REFRESH_HZ
        """One refresh of the display (from its reported rate; 60 Hz where it reports none)."""
        self.last_swap_s: float | None = None
        """``time.monotonic()`` when the last frame's buffer swap returned."""
        self.shown: list[int] = []
        """Every index shown, in order."""
        self._keys: collections.deque = collections.deque()
        self._window_closed = False
        self._screen: _Screen | None = None
        self._runner = _runner()
        if open:
            self.open()

    @property
    def frame_count(self) -> int:
        return len(self.images)

    @property
    def port(self) -> str:
        """The display, for messages."""
        d = self.display
        return f"display {d.index} ({d.name})" if d is not None else f"display {self.display_spec}"

    @property
    def is_open(self) -> bool:
        return self._screen is not None

    # -- on the SDL thread

    def _open_sdl(self) -> None:
        r = self._runner
        pg = r.init_video()
        disp = choose_display(r.displays(), self.display_spec)
        W, H = self.width, self.height
        if (W, H) != (disp.width, disp.height):
            where = f"display {disp.index} ({disp.name})"
            if W > disp.width or H > disp.height:
                raise ProjectorError(f"the frames are {W}x{H}, larger than the display's {disp.width}x{disp.height}; "
                                     f"set the display to the projector's native resolution ({W}x{H}) or make the "
                                     f"patterns for {disp.width}x{disp.height}", port=where, retryable=False)
            if not self.centre:
                raise ProjectorError(f"the frames are {W}x{H} but the display is {disp.width}x{disp.height}; set "
                                     f"the display to {W}x{H} (the projector's native resolution, so one pattern "
                                     f"pixel is one mirror), make the patterns for {disp.width}x{disp.height}, or "
                                     f"show them centred (--centre)", port=where, retryable=False)
        pos = _WINDOWPOS_CENTERED_DISPLAY | disp.index
        window = r.video.Window(self.title, size=(disp.width, disp.height), position=(pos, pos), borderless=True,
                                fullscreen_desktop=True, allow_high_dpi=True, always_on_top=True)
        try:
            renderer = r.video.Renderer(window, vsync=self.vsync)
            vp = renderer.get_viewport()
            if (vp.w, vp.h) != (disp.width, disp.height):
                raise ProjectorError(f"the display's mode is {disp.width}x{disp.height} pixels but a full-screen "
                                     f"window draws {vp.w}x{vp.h}: the OS scales this display; set its scaling to "
                                     f"100%", port=f"display {disp.index} ({disp.name})", retryable=False)
            texture = r.video.Texture(renderer, (W, H), streaming=True)
        except BaseException:
            window.destroy()
            raise
        pg.mouse.set_visible(False)
        self._screen = _Screen(window, renderer, texture, pg.Rect((disp.width - W) // 2, (disp.height - H) // 2, W, H))
        self.display = disp
        self.frame_period_s = 1.0 / (disp.refresh_hz or DEFAULT_REFRESH_HZ)
        self._window_closed = False
        r.listen(self._on_event)
        self._draw(None)
        log.info("display projector: %dx%d frames on %s%s", W, H, disp.describe(),
                 " (centred)" if (W, H) != (disp.width, disp.height) else "")

    def _draw(self, frame: np.ndarray | None) -> None:
        s = self._screen
        ren = s.renderer
        ren.draw_color = (0, 0, 0, 255)
        ren.clear()
        if frame is not None:
            rgb = np.ascontiguousarray(np.repeat(frame[:, :, None], 3, axis=2))
            surf = self._runner.pygame.image.frombuffer(rgb, (self.width, self.height), "RGB")
            s.texture.update(surf)
            ren.blit(s.texture, s.rect)
        ren.present()

    def _close_sdl(self) -> None:
        s, self._screen = self._screen, None
        self._runner.unlisten(self._on_event)
        if s is not None:
            s.window.destroy()
            self._runner.pygame.mouse.set_visible(True)

    def _on_event(self, ev) -> None:
        pg = self._runner.pygame
        if ev.type == pg.KEYDOWN:
            self._keys.append(pg.key.name(ev.key))
        elif ev.type in (pg.QUIT, pg.WINDOWCLOSE):
            self._window_closed = True

    # -- the device

    def open(self) -> None:
        """Open the full-screen window (showing black)."""
        if self._screen is None:
            self._runner.call(self._open_sdl)

    def _present(self, frame: np.ndarray | None) -> None:
        if self._window_closed:
            raise ProjectorError("the projector window was closed", port=self.port)
        if self._screen is None:
            raise ProjectorError("the projector window is not open", port=self.port)
        self._runner.call(self._draw, frame)
        self.last_swap_s = time.monotonic()

    def show(self, index: int) -> None:
        """Show frame ``index``; return after the buffer swap (with vsync) and ``latency_s``.

        Raises:
            ProjectorCommandError: index out of range.
            ProjectorError: the window was closed (``recover()`` reopens it).
        """
        index = int(index)
        if not 0 <= index < len(self.images):
            raise ProjectorCommandError(f"frame index {index} out of range (0..{len(self.images) - 1})", code=2,
                                        port=self.port, retryable=False)
        self._present(self.images[index])
        self.current_index = index
        self.shown.append(index)
        if self.latency_s > 0:
            time.sleep(self.latency_s)

    def blank(self) -> None:
        """Show black."""
        self._present(None)
        self.current_index = -1

    def poll_keys(self) -> list[str]:
        """Keys pressed on the projector window since the last call (pygame key names:
        ``"right"``, ``"q"``, ``"escape"``, ...)."""
        if self._runner._thread is None:
            self._runner.call(lambda: None)  # inline: handle the events now
        keys = []
        while self._keys:
            keys.append(self._keys.popleft())
        return keys

    @property
    def window_closed(self) -> bool:
        """The user closed the window (or the desktop asked it to quit)."""
        return self._window_closed

    def recover(self) -> None:
        """Reopen the window (after it was closed, or the display came back)."""
        self.close()
        self._window_closed = False
        self.open()

    def close(self) -> None:
        if self._screen is not None:
            self._runner.call(self._close_sdl)


def run_viewer(projector: DisplayProjector, *, start: int = 0, on_show: Callable[[int], None] | None = None,
               poll_s: float = 0.02) -> list[int]:
    """Step through the projector's frames by hand (for aiming the projector and camera).

    Keys (:data:`VIEWER_KEYS`): right / space / page down next, left / backspace / page up
    previous, home / end first / last, b black, q / escape quit. Returns when the user
    quits or closes the window.

    Args:
        projector: an open display projector.
        start: the frame shown first.
        on_show: called with the index shown after every change (-1 = black).
        poll_s: how often the keys are read.

    Returns:
        The indices shown, in order (-1 = black).
    """
    n = projector.frame_count
    if not 0 <= start < n:
        raise ValueError(f"start must be a frame index in 0..{n - 1}, got {start}")
    seen = []

    def go(i: int) -> None:
        if i < 0:
            projector.blank()
        else:
            projector.show(i)
        seen.append(i)
        if on_show is not None:
            on_show(i)

    cur = now = start
    go(cur)
    while True:
        for key in projector.poll_keys():
            action = VIEWER_KEYS.get(key)
            if action == "quit":
                return seen
            step = 0 if now < 0 else 1  # from black, next / previous bring the last frame back
            target = {"next": min(cur + step, n - 1), "previous": max(cur - step, 0), "first": 0, "last": n - 1,
                      "blank": -1}.get(action, now)
            if target != now:
                now = target
                cur = target if target >= 0 else cur
                go(now)
        if projector.window_closed:
            return seen
        time.sleep(poll_s)
