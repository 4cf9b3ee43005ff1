"""Projector latency: how long after a frame's buffer swap the camera sees it in full.

A projector on a display cable buffers one or two frames, and a DLP's colour wheel
needs a whole cycle, so the frame the computer swapped in is not yet the light on the
object; a camera grabbed too soon sees the old frame, a dim mix, or a torn frame (half
old, half new: a rolling shutter, or a frame caught mid-refresh).

:func:`measure_latency` measures the wait the capture needs, the way the capture uses
it: show a frame, wait a delay, grab once. It first records the camera's image of the
projector's black and white (the pixels that differ enough are the *lit* pixels), then,
for delays from 0 upward in steps of half a refresh, switches between black and white
(``trials`` times per delay, each from a steady old frame) and sorts each grab:

- ``new``: at least ``full_share`` of the lit pixels show the new frame;
- ``old``: at most ``1 - full_share`` do;
- ``mixed``: torn: some horizontal bands show the new frame, others still the old
  one. Such a frame is detected and grabbed again (``regrabs`` times at most) and
  counted; the delay it came at is too short;
- ``partial``: in between everywhere (a dim mix, a colour wheel part-way round).

The latency is the first delay from which every grab was ``new`` for ``confirm``
delays in a row; the rig file keeps it (plus a margin) as ``light.latency_s``
(:func:`write_rig_latency`) and ``ringscan capture`` waits that long after each frame.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import os
import time
from dataclasses import dataclass, field

import numpy as np

from ringscan.hardware.errors import CaptureError
from ringscan.pipeline.formats.atomic import atomic_write_json, read_json
from ringscan.pipeline.formats.errors import FormatError
from ringscan.pipeline.formats.rig import parse_rig

log = logging.getLogger(__name__)

__all__ = ["LatencySettings", "LatencyResult", "latency_frames", "classify_frame", "measure_latency",
           "read_rig_latency", "write_rig_latency", "VERDICTS"]

VERDICTS = ("new", "old", "mixed", "partial")
DEFAULT_FRAME_S = 1.0 / 60.0


@dataclass(frozen=True)
class LatencySettings:
    """How :func:`measure_latency` measures."""

    step_s: float | None = None
    """Delay step in seconds (None: half the projector's refresh period)."""
    max_s: float = 0.5
    """Longest delay tried; a projector slower than this is an error."""
    trials: int = 3
    """Switches (black to white, white to black, ...) per delay."""
    rest_s: float = 0.5
    """Time the old frame stays up before each switch (longer than the latency, so it is steady)."""
    confirm: int = 3
    """Delays in a row whose every grab must be new before the first of them is taken."""
    margin_frames: float = 1.0
    """Refresh periods added to the measured latency for the rig file (a margin for jitter)."""
    min_contrast: float = 24.0
    """Grey levels between the camera's white and black for a pixel to count as lit."""
    min_lit_share: float = 0.01
    """Least share of the camera's pixels that must be lit (else the camera does not see the projector)."""
    full_share: float = 0.98
    """Share of the lit pixels that must show the new frame for the frame to count as new."""
    bands: int = 8
    """Horizontal bands for telling a torn (mixed) frame from a dim (partial) one."""
    regrabs: int = 3
    """Further grabs after a mixed frame."""

    def __post_init__(self):
        for f in dataclasses.fields(self):
            v = getattr(self, f.name)
            if f.name == "step_s" and v is None:
                continue
            if f.name in ("trials", "confirm", "bands", "regrabs"):
                if isinstance(v, bool) or not isinstance(v, int) or v < (0 if f.name == "regrabs" else 1):
                    raise ValueError(f"{f.name} must be an integer >= {0 if f.name == 'regrabs' else 1}, got {v!r}")
            elif isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or v < 0:
                raise ValueError(f"{f.name} must be a finite number >= 0, got {v!r}")
        if self.step_s is not None and self.step_s <= 0:
            raise ValueError(f"step_s must be > 0, got {self.step_s!r}")
        if not 0.5 < self.full_share <= 1.0:
            raise ValueError(f"full_share must be in (0.5, 1], got {self.full_share!r}")
        if not 0 < self.min_lit_share <= 1.0 or self.min_contrast <= 0:
            raise ValueError("min_lit_share must be in (0, 1] and min_contrast > 0")


@dataclass(frozen=True)
class LatencyResult:
    """What :func:`measure_latency` found."""

    measured_s: float
    """First delay from which every grab showed the new frame in full."""
    latency_s: float
    """``measured_s`` plus the margin: the value for the rig file."""
    frame_period_s: float
    """The projector's refresh period used for the step and the margin."""
    step_s: float
    """Delay step."""
    lit_pixels: int
    """Camera pixels that see the projector's light."""
    mixed_frames: int
    """Torn frames seen (each grabbed again)."""
    delays: list = field(default_factory=list)
    """Per delay tried: ``{"delay_s", "grabs": [{"after_s", "verdict", "new_share", "regrabs": [...]}]}``."""

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)


def latency_frames(width: int, height: int) -> dict[str, np.ndarray]:
    """The two frames of the measurement, for a projector of ``width`` x ``height``:
    ``black`` (index 0) and ``white`` (index 1)."""
    if width < 1 or height < 1:
        raise ValueError(f"frame size must be positive, got {width}x{height}")
    return {"black": np.zeros((height, width), np.uint8), "white": np.full((height, width), 255, np.uint8)}


def classify_frame(image: np.ndarray, black: np.ndarray, white: np.ndarray, lit: np.ndarray, *, new_white: bool,
                   full_share: float = 0.98, bands: int = 8) -> tuple[str, float]:
    """Sort one grab of a switch between black and white.

    Args:
        image: the grab (H, W).
        black, white: the camera's images of the projector's black and white (H, W).
        lit: (H, W) bool, the pixels that see the projector's light.
        new_white: the switch was to white (else to black).
        full_share: share of lit pixels on the new side for ``new``.
        bands: horizontal bands for the torn-frame test.

    Returns:
        (verdict, share of lit pixels that show the new frame); verdict is one of
        ``new``, ``old``, ``mixed`` (some bands new, others old), ``partial``.
    """
    image = np.asarray(image)
    if image.shape != black.shape or black.shape != white.shape or lit.shape != black.shape:
        raise ValueError(f"image {image.shape}, black {black.shape}, white {white.shape} and lit {lit.shape} "
                         f"must have one shape")
    mid = (black.astype(np.float32) + white.astype(np.float32)) * 0.5
    img = image.astype(np.float32)
    is_new = (img > mid) if new_white else (img < mid)
    n_lit = int(lit.sum())
    if n_lit == 0:
        raise ValueError("no lit pixels")
    share = float((is_new & lit).sum()) / n_lit
    if share >= full_share:
        return "new", share
    if share <= 1.0 - full_share:
        return "old", share
    rows = np.nonzero(lit.any(axis=1))[0]
    edges = np.linspace(rows[0], rows[-1] + 1, bands + 1).astype(int)
    band_shares = []
    for r0, r1 in zip(edges[:-1], edges[1:]):
        m = lit[r0:r1]
        if m.sum():
            band_shares.append(float((is_new[r0:r1] & m).sum()) / float(m.sum()))
    if band_shares and max(band_shares) >= full_share and min(band_shares) <= 1.0 - full_share:
        return "mixed", share
    return "partial", share


def measure_latency(projector, camera, *, settings: LatencySettings = LatencySettings(), black: int = 0,
                    white: int = 1, frame_period_s: float | None = None) -> LatencyResult:
    """Measure how long after ``projector.show`` returns the camera sees the new frame in full.

    Args:
        projector: a ProjectorDevice holding a black frame at index ``black`` and a white
            one at ``white`` (:func:`latency_frames`), with no latency wait of its own.
        camera: a CameraDevice aimed at the projected light (a wall, a board, the
            turntable), as it will be used for capturing (same exposure, same flush).
        settings: how to measure.
        black, white: the frame indices.
        frame_period_s: the display's refresh period (default: the projector's
            ``frame_period_s``, else 1/60 s).

    Returns:
        The :class:`LatencyResult`.

    Raises:
        CaptureError: the camera does not see the projector, or no delay up to
            ``settings.max_s`` showed the new frame in full.
    """
    if frame_period_s is None:
        frame_period_s = float(getattr(projector, "frame_period_s", DEFAULT_FRAME_S) or DEFAULT_FRAME_S)
    if not frame_period_s > 0:
        raise ValueError(f"frame_period_s must be > 0, got {frame_period_s!r}")
    s = settings
    step = s.step_s if s.step_s is not None else frame_period_s / 2.0

    b_img, w_img, lit, n_lit = _reference_frames(projector, camera, s, black=black, white=white)
    log.info("latency: %d lit camera pixels (%.0f%%); step %.1f ms, up to %.0f ms", n_lit, 100.0 * n_lit / lit.size,
             step * 1e3, s.max_s * 1e3)

    now_white = True
    delays, mixed, run_start, run = [], 0, None, 0
    n_steps = int(math.floor(s.max_s / step + 1e-9)) + 1
    for k in range(n_steps):
        d = k * step
        grabs = []
        for _ in range(s.trials):
            time.sleep(s.rest_s)  # the old frame is steady
            new_white = not now_white
            projector.show(white if new_white else black)
            now_white = new_white
            t0 = time.monotonic()
            while (left := t0 + d - time.monotonic()) > 0:
                time.sleep(left)
            after = time.monotonic() - t0
            verdict, share = classify_frame(np.asarray(camera.grab()), b_img, w_img, lit, new_white=new_white,
                                            full_share=s.full_share, bands=s.bands)
            again = []
            while verdict == "mixed" and len(again) < s.regrabs:
                mixed += 1
                log.info("latency: a torn frame (%.0f%% new) %.1f ms after the swap; grabbing again", 100 * share,
                         after * 1e3)
                v2, sh2 = classify_frame(np.asarray(camera.grab()), b_img, w_img, lit, new_white=new_white,
                                         full_share=s.full_share, bands=s.bands)
                again.append({"after_s": time.monotonic() - t0, "verdict": v2, "new_share": sh2})
                if v2 != "mixed":
                    break
            if verdict == "mixed" and again and again[-1]["verdict"] == "mixed":
                log.warning("latency: the camera still sees torn frames after %d grabs (flicker, or a rolling shutter "
                            "beating with the refresh?)", len(again))
            grabs.append({"after_s": after, "verdict": verdict, "new_share": share, "regrabs": again})
        delays.append({"delay_s": d, "grabs": grabs})
        all_new = all(g["verdict"] == "new" for g in grabs)
        log.debug("latency: %.1f ms: %s", d * 1e3, " ".join(g["verdict"] for g in grabs))
        if all_new:
            run_start = d if run == 0 else run_start
            run += 1
            if run >= s.confirm:
                measured = run_start
                return LatencyResult(measured_s=measured, latency_s=measured + s.margin_frames * frame_period_s,
                                     frame_period_s=frame_period_s, step_s=step, lit_pixels=n_lit,
                                     mixed_frames=mixed, delays=delays)
        else:
            run = 0
    seen = ", ".join(f"{x['delay_s'] * 1e3:.0f} ms: " + "/".join(g["verdict"] for g in x["grabs"]) for x in delays[-3:])
    raise CaptureError(f"no delay up to {s.max_s * 1e3:.0f} ms showed the new frame in full {s.confirm} times in a "
                       f"row (last delays: {seen}); raise the longest delay (--max-delay), or check that nothing "
                       f"else changes the light (auto exposure, room light, the projector's dynamic contrast)")


def _reference_frames(projector, camera, s: LatencySettings, *, black: int, white: int):
    """The camera's steady black and white frames, the pixels the projector lights (white - black
    >= ``min_contrast``) and their count. Raises CaptureError where too few are lit."""
    projector.show(black)
    time.sleep(s.rest_s)
    b_img = np.asarray(camera.grab())
    projector.show(white)
    time.sleep(s.rest_s)
    w_img = np.asarray(camera.grab())
    if b_img.shape != w_img.shape or b_img.ndim != 2:
        raise CaptureError(f"the camera's frames changed shape ({b_img.shape} then {w_img.shape})")
    lit = (w_img.astype(np.float32) - b_img.astype(np.float32)) >= s.min_contrast
    n_lit = int(lit.sum())
    if n_lit < s.min_lit_share * lit.size:
        raise CaptureError(f"the camera does not see the projector: its white and black differ by {s.min_contrast:g} "
                           f"grey levels or more in only {n_lit} of {lit.size} pixels; aim the camera at the projected "
                           f"area, and set its exposure so that the white is bright but not saturated")
    return b_img, w_img, lit, n_lit


def read_rig_latency(path: str | os.PathLike) -> float:
    """The projector latency a rig file keeps (``light.latency_s``; 0 when absent).

    Raises:
        FormatError: not a rig file, or a latency that is not a number >= 0.
    """
    d = read_json(path)
    parse_rig(d, source=path)
    v = d["light"].get("latency_s", 0.0)
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or not 0 <= v <= 10.0:
        raise FormatError(path, f"light.latency_s: expected seconds in [0, 10], got {v!r}")
    return float(v)


def write_rig_latency(path: str | os.PathLike, latency_s: float) -> None:
    """Put the projector latency into a rig file (``light.latency_s``, seconds),
    keeping everything else in it; atomic.

    Raises:
        FormatError: the file is not a valid rig.
    """
    if isinstance(latency_s, bool) or not isinstance(latency_s, (int, float)) or not math.isfinite(latency_s) \
            or not 0 <= latency_s <= 10.0:
        raise ValueError(f"latency_s must be seconds in [0, 10], got {latency_s!r}")
    d = read_json(path)
    parse_rig(d, source=path)
    d["light"]["latency_s"] = round(float(latency_s), 4)
    atomic_write_json(path, d)
