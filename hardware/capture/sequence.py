"""The capture sequence: turn, show, grab, write, for every view and frame.

For each view the table turns to its angle and settles; for each frame the projector
shows it, the camera grabs, the frame is written atomically and scan.json, listing the
frames written so far, is rewritten atomically: the folder is a valid (maybe partial)
scan at every moment (docs/design.md §13). ``capture.json`` keeps the plan, the
settings, the table's last confirmed angle, the status and a log of runs; ``resume=True``
continues from there, capturing no frame twice (docs/design.md §14). A view's
``turntable_deg`` is the angle the table reached, not the planned one.

A device fault is retried (after the device's ``recover()``) up to ``settings.retries``
times, then the capture stops with :class:`CaptureError`, leaving the partial scan; a
turntable fault that leaves the angle unknown is never retried, and resuming needs the
user's word (``table_at``). Ctrl-C always stops a capture (:class:`InterruptGuard`).
Faults and what each does: docs/hardware.md.
"""

from __future__ import annotations

import dataclasses
import datetime
import json
import logging
import math
import os
import signal
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ringscan.hardware.errors import CameraError, CaptureError, DeviceError, ProjectorError, TurntableError
from ringscan.pipeline.formats.atomic import atomic_write_json, read_json
from ringscan.pipeline.formats.errors import FormatError
from ringscan.pipeline.formats.images import write_image
from ringscan.pipeline.formats.patterns import PatternSpec, frame_names
from ringscan.pipeline.formats.progress import progress_bar
from ringscan.pipeline.formats.rig import Rig, rig_to_dict
from ringscan.pipeline.formats.frame_store import (STORE_NAME, create_store, is_store, open_store,
                                                   remove_stale_chunk_temporaries, write_frame)
from ringscan.pipeline.formats.scan import Scan, View, check_frame_bits, load_scan, packed_view, save_scan

log = logging.getLogger(__name__)

__all__ = ["CAPTURE_FORMAT", "CaptureSettings", "InterruptGuard", "capture_scan", "resume_angle",
           "read_capture_state", "plan_angles", "view_name"]

CAPTURE_FORMAT = "ringscan.capture/1"
CAPTURE_FILE = "capture.json"
IMAGE_FORMATS = ("png", "tiff", "packed")
"""Frame files: PNG, uncompressed TIFF, or ``packed``: one frame store per view (``<view>/frames.zarr``),
frames appended as they arrive."""
PLAN_TOLERANCE_DEG = 1.0
"""How far a view's recorded (reached) angle may lie from its planned angle: a
reached angle is within half a motor step of the plan (0.056 deg at 8.889 steps/deg,
0.9 deg for a direct drive at full steps)."""


class InterruptGuard:
    """Ctrl-C that cannot be lost.

    Python ignores an exception raised inside ``__del__`` (it only prints "Exception
    ignored in ..."), so a SIGINT whose ``KeyboardInterrupt`` lands in a finalizer (a
    Warp array's, say) would let a capture go on and exit 0. Inside this context
    manager SIGINT sets :attr:`interrupted` and raises ``KeyboardInterrupt``;
    :meth:`check` raises it again if it was swallowed, and so does leaving the
    block. Only the main thread can install the handler; elsewhere it does nothing.
    """

    def __init__(self):
        self.interrupted = False
        """A SIGINT arrived."""
        self._prev = None
        self._installed = False

    def _handle(self, signum, frame):
        self.interrupted = True
        raise KeyboardInterrupt

    def __enter__(self) -> InterruptGuard:
        if threading.current_thread() is threading.main_thread():
            self._prev = signal.getsignal(signal.SIGINT)
            signal.signal(signal.SIGINT, self._handle)
            self._installed = True
        return self

    def check(self) -> None:
        """Raise ``KeyboardInterrupt`` if a SIGINT arrived."""
        if self.interrupted:
            raise KeyboardInterrupt

    def __exit__(self, exc_type, exc, tb):
        if self._installed:
            prev = self._prev if self._prev is not None else signal.default_int_handler
            signal.signal(signal.SIGINT, prev)
            self._installed = False
        if exc_type is None:
            self.check()
        return False


@dataclass(frozen=True)
class CaptureSettings:
    """Timing and fault handling of a capture (saved in capture.json)."""

    turntable_settle_s: float = 0.5
    """Wait after the table reports Idle, so the object stops wobbling."""
    projector_settle_s: float = 0.05
    """Wait after the projector acknowledges a frame, before the camera grabs
    (covers the display's latch and the camera's rolling exposure)."""
    feed_deg_per_min: float = 600.0
    """Table speed for moves (G-code F word); slow enough that the object does not slip."""
    command_timeout_s: float = 2.0
    """Longest wait for a device's reply to one command."""
    motion_timeout_s: float = 30.0
    """Time allowed for a move on top of its length at the feed rate."""
    retries: int = 3
    """Further attempts of a failed device operation (after recovering the device)."""
    retry_delay_s: float = 0.5
    """Pause before recovering a device and retrying."""
    image_format: str = "png"
    """Frame files: "png" or "tiff" (both lossless, 8 or 16 bit)."""

    def __post_init__(self):
        for f in dataclasses.fields(self):
            v = getattr(self, f.name)
            if f.name == "image_format":
                if v not in IMAGE_FORMATS:
                    raise ValueError(f"image_format must be one of {IMAGE_FORMATS}, got {v!r}")
            elif f.name == "retries":
                if isinstance(v, bool) or not isinstance(v, int) or v < 0:
                    raise ValueError(f"retries must be an integer >= 0, got {v!r}")
            elif isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or v < 0:
                raise ValueError(f"{f.name} must be a finite number >= 0, got {v!r}")
        if self.feed_deg_per_min <= 0 or self.command_timeout_s <= 0:
            raise ValueError("feed_deg_per_min and command_timeout_s must be > 0")

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, d: dict, *, source=None) -> CaptureSettings:
        """Settings from a JSON object; unknown keys and bad values raise FormatError."""
        if not isinstance(d, dict):
            raise FormatError(source, "settings: expected an object")
        known = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(set(d) - known)
        if unknown:
            raise FormatError(source, f"settings: unknown key(s) {', '.join(unknown)} "
                                      f"(known: {', '.join(sorted(known))})")
        try:
            return cls(**d)
        except (TypeError, ValueError) as e:
            raise FormatError(source, f"settings: {e}") from None


def view_name(i: int) -> str:
    """Folder name of view ``i``."""
    return f"view_{i:03d}"


MAX_VIEWS = 10000
"""Most views of a capture: a view every 0.036 degrees of a turn (angles go to the table rounded to 0.001 degrees);
the plan, capture.json and scan.json hold every view (a scan.json of 10 000 views is ~3 MB)."""


def plan_angles(views: int, step_deg: float | None = None, start_deg: float = 0.0) -> list[float]:
    """Turntable angles of the views (degrees, rounded to 0.001 as G-code sends them).

    Default step: one full turn over the views (360 / views).
    """
    if isinstance(views, bool) or not isinstance(views, int) or not 1 <= views <= MAX_VIEWS:
        raise ValueError(f"views must be an integer from 1 to {MAX_VIEWS}, got {views!r}")
    step = 360.0 / views if step_deg is None else float(step_deg)
    if not math.isfinite(step) or not math.isfinite(start_deg):
        raise ValueError("step and start angles must be finite")
    return [round(start_deg + i * step, 3) + 0.0 for i in range(views)]


def read_capture_state(folder: str | os.PathLike) -> dict:
    """The capture.json of a scan folder, checked."""
    path = Path(folder) / CAPTURE_FILE
    d = read_json(path)
    if d.get("format") != CAPTURE_FORMAT:
        raise FormatError(path, f"format: unknown capture state format {d.get('format')!r} "
                                f"(this version reads {CAPTURE_FORMAT!r})")
    plan = d.get("plan")
    if not isinstance(plan, dict) or not isinstance(plan.get("angles"), list) or not plan["angles"]:
        raise FormatError(path, "plan.angles: expected a non-empty list of angles")
    for i, a in enumerate(plan["angles"]):
        if isinstance(a, bool) or not isinstance(a, (int, float)) or not math.isfinite(a):
            raise FormatError(path, f"plan.angles[{i}]: expected a finite number, got {a!r}")
    table = d.get("table")
    if not isinstance(table, dict) or not isinstance(table.get("deg"), (int, float)):
        raise FormatError(path, "table.deg: expected the table's last confirmed angle")
    mv = table.get("moving_to")
    if mv is not None and (isinstance(mv, bool) or not isinstance(mv, (int, float))):
        raise FormatError(path, f"table.moving_to: expected a number or null, got {mv!r}")
    reaches = table.get("reaches")
    if reaches is not None and (isinstance(reaches, bool) or not isinstance(reaches, (int, float))
                                or not math.isfinite(reaches)):
        raise FormatError(path, f"table.reaches: expected a finite number or null, got {reaches!r}")
    if not isinstance(table.get("known", True), bool):
        raise FormatError(path, f"table.known: expected true or false, got {table.get('known')!r}")
    if not isinstance(d.get("runs", []), list):
        raise FormatError(path, "runs: expected a list")
    return d


def resume_angle(folder: str | os.PathLike, table_at: float | None = None) -> float:
    """Where the table stands for a resumed capture.

    ``table_at`` (the user's word) wins; else the last confirmed angle, unless a
    move was under way when the capture stopped or the angle became unknown (an
    alarm, a table found turning): then this raises CaptureError asking for
    ``table_at``.
    """
    folder = Path(folder)
    _require_capture(folder)
    state = read_capture_state(folder)
    if table_at is not None:
        return float(table_at)
    mv = state["table"].get("moving_to")
    if mv is not None:
        # the hint is the angle the motor's whole steps reach, not the one asked for
        end = state["table"].get("reaches")
        end = mv if end is None else end
        raise CaptureError(f"{Path(folder) / CAPTURE_FILE}: the turntable was moving from {state['table']['deg']:g} "
                           f"to {mv:g} deg when the capture stopped, so its angle is unknown; check where it "
                           f"stands and resume with --table-at DEG (e.g. --table-at {end:g} if the move finished)",
                           folder=folder)
    if state["table"].get("known", True) is False:
        raise CaptureError(f"{Path(folder) / CAPTURE_FILE}: the turntable's angle became unknown when the capture "
                           f"stopped (last confirmed at {state['table']['deg']:g} deg); check where it stands and "
                           f"resume with --table-at DEG", folder=folder)
    return float(state["table"]["deg"])


def _now() -> str:
    return datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds")


def _same(a: dict, b: dict) -> bool:
    return json.dumps(a, sort_keys=True, default=float) == json.dumps(b, sort_keys=True, default=float)


def _clean_temp_files(folder: Path) -> int:
    """Remove temporary files that a killed writer left (``.<stem>.*.tmp<suffix>``)."""
    n = 0
    for d in [folder] + [p for p in folder.iterdir() if p.is_dir()]:
        for p in d.iterdir():
            if p.name.startswith(".") and ".tmp" in p.name and p.is_file():
                p.unlink()
                n += 1
    return n


def _new_capture(out: Path, rig: Rig | None, patterns: PatternSpec | None, views: int | None,
                 step_deg: float | None, start_deg: float, frame_bits: int | None = None) -> tuple[Scan, dict]:
    if rig is None or patterns is None or views is None:
        raise ValueError("a new capture needs the rig, the patterns and the number of views")
    if (out / "scan.json").exists():
        raise CaptureError(f"{out} already holds a scan; use --resume to continue it, or choose another folder",
                           folder=out)
    if out.exists() and (not out.is_dir() or any(out.iterdir())):
        raise CaptureError(f"{out} exists and is not an empty folder; choose another folder", folder=out)
    lw, lh = getattr(rig.light, "width", 0), getattr(rig.light, "height", 0)
    if lw and (patterns.width, patterns.height) != (lw, lh):
        raise ValueError(f"patterns are {patterns.width}x{patterns.height}, but the rig's projector is {lw}x{lh}")
    angles = plan_angles(views, step_deg, start_deg)
    out.mkdir(parents=True, exist_ok=True)
    state = {"format": CAPTURE_FORMAT,
             "plan": {"views": views, "step_deg": 360.0 / views if step_deg is None else float(step_deg),
                      "start_deg": float(start_deg), "angles": angles},
             "settings": None, "table": {"deg": 0.0, "moving_to": None}, "status": "new", "error": None, "runs": []}
    atomic_write_json(out / CAPTURE_FILE, state)
    scan = Scan(folder=out, rig=rig, patterns=patterns, views=(), frame_bits=frame_bits)
    save_scan(scan)
    return scan, state


def _require_capture(out: Path) -> None:
    if not (out / "scan.json").is_file():
        raise CaptureError(f"nothing to resume: {out} holds no scan.json", folder=out)
    if not (out / CAPTURE_FILE).is_file():
        raise CaptureError(f"cannot resume: {out} holds no {CAPTURE_FILE} (not made by 'ringscan capture')",
                           folder=out)


def _open_for_resume(out: Path, rig: Rig | None, patterns: PatternSpec | None, views: int | None,
                     step_deg: float | None, start_deg: float | None) -> tuple[Scan, dict]:
    _require_capture(out)
    state = read_capture_state(out)
    scan = load_scan(out, check_files=False, allow_incomplete=True)
    src = out / "scan.json"
    if rig is not None and not _same(rig_to_dict(rig), rig_to_dict(scan.rig)):
        raise CaptureError(f"{src}: the rig given differs from the rig of the capture being resumed", folder=out)
    if patterns is not None and not _same(patterns.to_dict(), scan.patterns.to_dict()):
        raise CaptureError(f"{src}: the patterns given differ from those of the capture being resumed", folder=out)
    angles = state["plan"]["angles"]
    if views is not None or step_deg is not None or start_deg is not None:
        want = plan_angles(views if views is not None else len(angles),
                           step_deg if step_deg is not None else state["plan"].get("step_deg"),
                           start_deg if start_deg is not None else state["plan"].get("start_deg", 0.0))
        if want != angles:
            raise CaptureError(f"{out / CAPTURE_FILE}: the capture being resumed has {len(angles)} views at "
                               f"{angles} deg; the options given ask for {want}", folder=out)
    if len(scan.views) > len(angles):
        raise FormatError(src, f"views: {len(scan.views)} views, but the capture plan has {len(angles)}")
    kept = []
    for i, v in enumerate(scan.views):
        if v.name != view_name(i) or abs(v.turntable_deg - angles[i]) > PLAN_TOLERANCE_DEG:
            raise FormatError(src, f"views[{i}]: {v.name} at {v.turntable_deg:g} deg does not match the capture "
                                   f"plan ({view_name(i)} at {angles[i]:g} deg)")
        frames = {}
        store = open_store(out / v.packed) if v.packed is not None and is_store(out / v.packed) else None
        for k, rel in v.frames.items():
            if (store.chunk_path(store.index(k)).is_file() if store is not None and k in store.names
                    else v.packed is None and (out / rel).is_file()):
                frames[k] = rel
            else:
                log.warning("capture: %s frame %s listed but missing on disk; it will be captured again", v.name, k)
        view = View(name=v.name, turntable_deg=v.turntable_deg, frames=frames)
        kept.append(packed_view(view, v.packed, list(frames)) if v.packed is not None and frames else view)
    n = _clean_temp_files(out)
    if n:
        log.info("capture: removed %d temporary file(s) left by an interrupted write", n)
    scan = dataclasses.replace(scan, views=tuple(kept))
    save_scan(scan)
    _settle_killed_run(out, state, sum(len(v.frames) for v in kept))
    return scan, state


def _settle_killed_run(out: Path, state: dict, listed: int) -> None:
    """Bring the record of a run that was killed (it never got to say how it ended)
    up to date from scan.json, which is rewritten after every frame."""
    runs = state.get("runs") or []
    if not runs or not isinstance(runs[-1], dict) or runs[-1].get("result") != "running":
        return
    run = runs[-1]
    before = sum(r.get("frames", 0) for r in runs[:-1] if isinstance(r, dict) and isinstance(r.get("frames"), int))
    mtime = (out / "scan.json").stat().st_mtime
    run["frames"] = max(listed - before, 0)
    run["result"] = "killed"
    run["ended"] = datetime.datetime.fromtimestamp(mtime, datetime.timezone.utc).isoformat(timespec="seconds")
    state["status"] = "killed"
    state["error"] = state.get("error") or "the process was killed (no word from it); the record was brought up " \
                                            "to date from scan.json on resume"
    atomic_write_json(out / CAPTURE_FILE, state)
    log.info("capture: the previous run was killed after %d frame(s); its record is brought up to date",
             run["frames"])


def _view_store(path: Path, names: list[str], img: np.ndarray, camera):
    """The frame store of a view being captured: a new one, or the one a killed run left."""
    if is_store(path):
        info = open_store(path)
        if info.names != tuple(names) or (info.height, info.width) != img.shape:
            raise FormatError(path / "zarr.json", "a frame store of other frames is in the way of this view's")
        remove_stale_chunk_temporaries(info)
        return info
    return create_store(path, names, height=img.shape[0], width=img.shape[1], dtype=img.dtype)


def _check_frame_count(projector, patterns: PatternSpec, out: Path) -> None:
    n = len(frame_names(patterns))
    if projector.frame_count != n:
        raise CaptureError(f"the projector holds {projector.frame_count} frames, the {patterns.codec} codec "
                           f"needs {n}", folder=out)


def _device_of(err: DeviceError, turntable, projector, camera):
    if isinstance(err, TurntableError):
        return turntable
    if isinstance(err, ProjectorError):
        return projector
    if isinstance(err, CameraError):
        return camera
    return None


def _with_retries(what: str, fn: Callable, settings: CaptureSettings, devices: tuple):
    """Run ``fn``; on a retryable device fault recover that device and try again."""
    attempt = 0
    while True:
        try:
            return fn()
        except DeviceError as e:
            if not e.retryable or not e.position_known or attempt >= settings.retries:
                raise
            err = e
        while True:
            attempt += 1
            log.warning("capture: %s failed: %s; retry %d of %d", what, err, attempt, settings.retries)
            time.sleep(settings.retry_delay_s)
            dev = _device_of(err, *devices)
            try:
                if dev is not None:
                    dev.recover()
                break
            except DeviceError as e:
                if not e.retryable or attempt >= settings.retries:
                    raise
                err = e


def capture_scan(out: str | os.PathLike, *, camera, projector, turntable, rig: Rig | None = None,
                 patterns: PatternSpec | None = None, views: int | None = None, step_deg: float | None = None,
                 start_deg: float | None = None, settings: CaptureSettings = CaptureSettings(), resume: bool = False,
                 table_at: float | None = None, progress: bool = True,
                 on_view: Callable[[Scan, View], None] | None = None, frame_bits: int | None = None) -> Scan:
    """Capture a scan into ``out``, or resume an interrupted capture there.

    Args:
        out: the scan folder (new or empty; with ``resume``, the interrupted one).
        camera: a CameraDevice.
        projector: a ProjectorDevice holding the codec's frames in frame order.
        turntable: a TurntableDevice; its current pose is angle 0 of a new capture.
        rig: the rig (required for a new capture; when resuming, checked against the scan's).
        patterns: the pattern set (as rig).
        views: number of views (as rig).
        step_deg: angle between views (default 360 / views).
        start_deg: angle of the first view (default 0).
        settings: timing and retries.
        resume: continue the capture in ``out``.
        table_at: when resuming, where the table stands now: the user's word, declared
            to the controller. Default: the last confirmed angle, which needs the
            turntable to know its angle (``turntable.position_known``); a move under
            way when the capture stopped, an alarm, or a table found turning makes
            it unknown, and then the capture stops asking for ``table_at``.
        progress: show a progress bar.
        on_view: called with (scan, view) after each view is complete (e.g. to start
            reconstructing it while the next one is captured).
        frame_bits: the bits the camera's frames hold (8, or 9..16 for 16-bit frames:
            12 for a 12-bit camera's values 0..4095), written as scan.json's
            ``frame_bits`` (docs/formats.md); every frame grabbed is checked against it.
            None: the frames' own bits (a resumed capture: the scan's).

    Returns:
        The complete scan (loaded back from disk).

    Raises:
        CaptureError: a device fault that retries did not cure; the folder holds a
            valid partial scan and ``resume`` continues it.
        KeyboardInterrupt: Ctrl-C (capture.json says "interrupted").
        FormatError, ValueError: bad input (nothing captured).

    Size: a public function (ringscan capture's): the scan folder, the three devices and its documented
    keyword-only options, one per user-facing setting (rig, patterns, views and angles, settings, resuming,
    progress, the per-view callback, frame bits).
    """
    out = Path(out)
    if frame_bits is not None:
        check_frame_bits(frame_bits, where="frame_bits")
    if not resume and patterns is not None:
        _check_frame_count(projector, patterns, out)
    if resume:
        table_deg = resume_angle(out, table_at)
        if frame_bits is not None:
            _require_capture(out)
            had = load_scan(out, check_files=False, allow_incomplete=True).frame_bits
            if had != frame_bits:
                raise CaptureError(f"{out / 'scan.json'}: the capture being resumed has frame_bits "
                                   f"{'absent' if had is None else had}, not {frame_bits}", folder=out)
        scan, state = _open_for_resume(out, rig, patterns, views, step_deg, start_deg)
    else:
        scan, state = _new_capture(out, rig, patterns, views, step_deg, 0.0 if start_deg is None else start_deg,
                                   frame_bits)
        table_deg = 0.0
    _check_frame_count(projector, scan.patterns, out)
    run = _CaptureRun(out, scan, state, camera=camera, projector=projector, turntable=turntable, settings=settings,
                      table_deg=table_deg, declared=not resume or table_at is not None)
    run.run(progress=progress, on_view=on_view)
    try:
        projector.blank()
    except DeviceError as e:
        log.warning("capture: could not blank the projector at the end: %s", e)
    log.info("capture: %s complete (%d frames this run)", out, run.record["frames"])
    return load_scan(out)


class _CaptureRun:
    """One run of the capture sequence over a new or resumed scan folder: the devices,
    the plan, the scan written so far, and this run's record in capture.json.

    Args:
        table_deg: where the table stands at the start.
        declared: ``table_deg`` is a definition (a new capture) or the user's word
            (``table_at``), not a claim that the turntable must confirm.
    """

    def __init__(self, out: Path, scan: Scan, state: dict, *, camera, projector, turntable,
                 settings: CaptureSettings, table_deg: float, declared: bool):
        """Hold a capture's folder, scan, state and devices, and start this run's record in the state.

        Size: a private class built once by capture_scan: its arguments are the folder, scan and state it
        writes, the three devices, and the settings and table angle capture_scan has already resolved.
        """
        self.out, self.scan, self.state, self.settings = out, scan, state, settings
        self.camera, self.projector, self.turntable = camera, projector, turntable
        self.devices = (turntable, projector, camera)
        self.table_deg, self.declared = table_deg, declared
        self.names = frame_names(scan.patterns)
        self.angles = [float(a) for a in state["plan"]["angles"]]
        self.views = list(scan.views)
        self.record = {"started": _now(), "ended": None, "frames": 0, "result": "running"}
        state["settings"] = settings.to_dict()
        state["status"] = "running"
        state["error"] = None
        state["table"] = {"deg": table_deg, "moving_to": None, "known": True}
        state["runs"] = list(state.get("runs", [])) + [self.record]
        self.bar = None
        self.guard = InterruptGuard()

    def write_state(self) -> None:
        atomic_write_json(self.out / CAPTURE_FILE, self.state)

    def run(self, *, progress: bool, on_view) -> None:
        """Capture every frame not yet on disk, view by view; capture.json says how the run ended."""
        self.write_state()
        done = sum(len([n for n in self.names if n in v.frames]) for v in self.views)
        self.bar = progress_bar(total=len(self.angles) * len(self.names), initial=done, unit="frame",
                                desc=f"capture {self.out.name}", disable=not progress)
        log.info("capture: %s, %d views x %d frames, %d already captured", self.out, len(self.angles),
                 len(self.names), done)
        try:
            with self.guard:
                self._retry("declaring the table angle", self._declare_start)
                self._retry("enabling the table motor", lambda: self.turntable.enable_motor(True))
                for i, angle in enumerate(self.angles):
                    self._capture_view(i, angle, on_view)
        except DeviceError as e:
            raise CaptureError(self._stopped_by(e), folder=self.out, cause=e) from e
        except KeyboardInterrupt:
            self.record["result"] = self.state["status"] = "interrupted"
            self.state["error"] = "interrupted by the user"
            if self.state["table"]["moving_to"] is not None:
                self.state["table"]["known"] = False
            raise
        except BaseException as e:
            self.record["result"] = self.state["status"] = "stopped"
            self.state["error"] = f"{type(e).__name__}: {e}"
            raise
        else:
            self.record["result"] = self.state["status"] = "complete"
        finally:
            self.bar.close()
            self.record["ended"] = _now()
            self.write_state()

    def _retry(self, what: str, fn: Callable):
        return _with_retries(what, fn, self.settings, self.devices)

    def _declare_start(self) -> None:
        """Tell the controller where the table stands (refused when that is a claim it cannot back)."""
        turntable = self.turntable
        if not self.declared and not turntable.position_known:
            raise TurntableError(f"{turntable.unknown_reason}; the last confirmed angle ({self.table_deg:g} deg) "
                                 f"cannot be trusted", port=getattr(turntable, "port", None), retryable=False,
                                 position_known=False)
        turntable.set_position(self.table_deg)

    def _capture_view(self, i: int, angle: float, on_view) -> None:
        """Turn to view ``i`` and capture its missing frames, writing scan.json after each."""
        view = self.views[i] if i < len(self.views) else None
        if view is not None and all(n in view.frames for n in self.names):
            return
        # a view begun in an earlier run goes on at the angle its frames were taken at
        target = view.turntable_deg if view is not None else angle
        if abs(self.turntable.position_deg - target) > 1e-6:
            self._turn_to(target)
        if view is None:
            view = View(name=view_name(i), turntable_deg=self.turntable.position_deg, frames={})
            self.views.append(view)
        elif abs(self.turntable.position_deg - view.turntable_deg) > PLAN_TOLERANCE_DEG:
            raise CaptureError(f"{view.name}'s frames were taken at {view.turntable_deg:g} deg, the table "
                               f"stands at {self.turntable.position_deg:g} deg", folder=self.out)
        frames = dict(view.frames)
        store = None
        self.bar.set_postfix_str(view.name)
        for j, fname in enumerate(self.names):
            if fname in frames:
                continue
            img = self._retry(f"{view.name} frame {fname}", lambda j=j: self._show_and_grab(j))
            if self.settings.image_format == "packed":
                if store is None:  # made with every frame's name (a resumed view keeps its own)
                    store = _view_store(self.out / view.name / STORE_NAME, self.names, img, self.camera)
                if img.dtype != store.dtype:
                    raise CameraError(f"camera delivers {img.dtype} frames, {store.path} holds {store.dtype}",
                                      port=getattr(self.camera, "source", None), retryable=False)
                write_frame(store, fname, img)
                frames[fname] = f"{view.name}/{STORE_NAME}"
                self.views[i] = packed_view(view, frames[fname], [n for n in self.names if n in frames])
            else:
                rel = f"{view.name}/{fname}.{self.settings.image_format}"
                write_image(self.out / rel, img)
                frames[fname] = rel
                self.views[i] = View(name=view.name, turntable_deg=view.turntable_deg, frames=dict(frames))
            self.scan = dataclasses.replace(self.scan, views=tuple(self.views))
            save_scan(self.scan)
            self.record["frames"] += 1
            self.bar.update(1)
            self.guard.check()
        if on_view is not None:
            on_view(self.scan, self.views[i])
            self.guard.check()

    def _turn_to(self, target: float) -> None:
        """Move the table, with capture.json naming the target while it moves; then settle."""
        turntable = self.turntable
        self.state["table"] = {"deg": turntable.position_deg, "moving_to": target, "known": True,
                               "reaches": turntable.reachable_deg(target)}
        self.write_state()
        self._retry(f"turning to {target:g} deg", lambda: turntable.move_to(target))
        self.state["table"] = {"deg": turntable.position_deg, "moving_to": None, "known": True}
        self.write_state()
        self.guard.check()
        if self.settings.turntable_settle_s > 0:
            time.sleep(self.settings.turntable_settle_s)

    def _show_and_grab(self, j: int) -> np.ndarray:
        """Show frame ``j``, wait for the projector, grab one camera image (checked against the rig and
        the scan's frame_bits)."""
        self.projector.show(j)
        if self.settings.projector_settle_s > 0:
            time.sleep(self.settings.projector_settle_s)
        img = self.camera.grab()
        cam = self.scan.rig.camera
        if img.shape != (cam.height, cam.width):
            raise CameraError(f"camera delivers {img.shape[1]}x{img.shape[0]} frames, the rig's camera is "
                              f"{cam.width}x{cam.height}", port=getattr(self.camera, "source", None),
                              retryable=False)
        bits = self.scan.frame_bits
        if bits is not None:  # a wrong setting found at the first frame, not at the reconstruction
            depth = 8 if img.dtype == np.uint8 else 16
            top = int(img.max()) if depth == 16 and 8 < bits < 16 else 0
            if (depth == 8) != (bits == 8) or top > (1 << bits) - 1:
                got = f"{depth}-bit frames" + (f" holding {top}" if top else "")
                raise CameraError(f"camera delivers {got}, but frame_bits (--frame-bits) says {bits} bits"
                                  f"{f' (at most {(1 << bits) - 1})' if top else ''}",
                                  port=getattr(self.camera, "source", None), retryable=False)
        return img

    def _stopped_by(self, e: DeviceError) -> str:
        """Record a run stopped by a device fault; returns the message that says how to go on."""
        self.record["result"] = self.state["status"] = "stopped"
        target = self.state["table"]["moving_to"]
        if e.position_known:  # the move was refused, or the fault came before or after it
            self.state["table"] = {"deg": self.turntable.position_deg, "moving_to": None, "known": True}
        else:
            self.state["table"]["known"] = False
        if not e.position_known:
            where = (f"The turntable may have stopped part way to {target:g} deg" if target is not None
                     else "The turntable's angle is unknown")
            msg = (f"capture stopped: {e}. {where}. The scan in {self.out} is valid but incomplete; check the "
                   f"table's angle and continue with --resume --table-at DEG")
        else:
            tried = f" after {self.settings.retries} retries" if e.retryable and self.settings.retries else ""
            msg = (f"capture stopped{tried}: {e}. The scan in {self.out} is valid but incomplete; fix the device "
                   f"and continue with --resume")
        self.state["error"] = msg
        return msg
