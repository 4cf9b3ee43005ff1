"""When is a reconstruction done? The one place that decides (``reconstruct --resume``,
``ringscan batch`` and live reconstruction during a capture all ask here).

A view's result is done when it was made from the same inputs with the same settings
(a per-view content hash, :func:`hash_inputs`: the parsed rig, the patterns, the
resolved settings but ``threads``, scan.json's ``frame_bits`` where set, the view's
scan.json entry, each frame file's size and modification time) and its PLY is whole
and holds the points the report says;
otherwise it is redone and :class:`DoneCheck` says why. A scan is done when every view
asked for is done. Why sizes and times rather than a hash of the bytes, and what that
misses: docs/design.md §14.
"""

from __future__ import annotations

import hashlib
import json
import os
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

from ringscan.pipeline.formats.atomic import json_safe, read_json
from ringscan.pipeline.formats.errors import FormatError
from ringscan.pipeline.formats.patterns import frame_names
from ringscan.pipeline.formats.ply import check_ply
from ringscan.pipeline.formats.rig import rig_to_dict
from ringscan.pipeline.formats.scan import Scan, frame_files
from ringscan.pipeline.formats.settings import settings_to_dict

__all__ = ["REPORT_FORMAT", "HASH_RECIPE", "InputHashes", "DoneCheck", "hash_inputs", "check_done"]

REPORT_FORMAT = "ringscan.report/1"
"""Format of a reconstruction's ``report.json``."""

HASH_RECIPE = "ringscan.inputs/1"
"""Version of the hash recipe; a report made with another one is redone."""

_IGNORED_SETTINGS = ("threads",)
"""Settings that do not change a result (not hashed)."""


def _digest(obj) -> str:
    text = json.dumps(json_safe(obj), sort_keys=True, separators=(",", ":"))
    return hashlib.sha256(text.encode()).hexdigest()


@dataclass(frozen=True)
class InputHashes:
    """Content hashes (SHA-256, hex) of what a reconstruction is made from."""

    rig: str
    """The parsed rig."""
    patterns: str
    """The patterns block."""
    settings: str
    """The resolved settings (without ``threads``)."""
    views: dict[str, str]
    """View name -> hash of the above, the view's scan.json entry and its frame files' sizes and times."""
    scan: str
    """Hash of everything above, for the views asked for."""

    def to_dict(self) -> dict:
        """The report's ``inputs`` block (the per-view hashes live in each view's entry)."""
        return {"recipe": HASH_RECIPE, "hash": self.scan, "rig": self.rig, "patterns": self.patterns,
                "settings": self.settings}


def _frame_stat(path: Path):
    try:
        st = os.stat(path)
    except (OSError, ValueError):
        return None
    return [st.st_size, st.st_mtime_ns]


def hash_inputs(scan: Scan, settings, *, views: list[str] | None = None,
                stat: Callable[[Path], list | None] | None = None) -> InputHashes:
    """Hash the inputs of a reconstruction of ``scan`` with ``settings`` (see the module docstring).

    Args:
        scan: a loaded scan.
        settings: the resolved settings (a dataclass, e.g. ``ReconstructSettings``).
        views: names of the views asked for (default: all); ``views`` of the result
            holds those only.
        stat: a frame file -> ``[size, modification time in ns]`` (None when missing);
            default ``os.stat``. A scan on object storage, staged without its frames,
            gives its objects' sizes and times (``formats.storage``).
    """
    stat = _frame_stat if stat is None else stat
    sd = settings_to_dict(settings)
    for k in _IGNORED_SETTINGS:
        sd.pop(k, None)
    base = {"recipe": HASH_RECIPE, "rig": _digest(rig_to_dict(scan.rig)),
            "patterns": _digest(scan.patterns.to_dict()), "settings": _digest(sd)}
    if scan.frame_bits is not None:  # how the frames are read (absent: the hashes of earlier scans stay)
        base["frame_bits"] = scan.frame_bits
    names = frame_names(scan.patterns)
    want = None if views is None else set(views)
    per_view = {}
    for index, v in enumerate(scan.views):
        if want is not None and v.name not in want:
            continue
        entry = {"name": v.name, "index": index, "turntable_deg": v.turntable_deg,
                 "frames": {n: v.frames.get(n) for n in names}}
        where = frame_files(scan, v)  # a packed view's frames: their chunk files
        files = {n: stat(where[n]) if n in v.frames else None for n in names}
        if v.camera2 is not None:  # camera 2's frames are inputs too
            entry["camera2"] = {n: v.camera2.frames.get(n) for n in names}
            where2 = frame_files(scan, v.camera2)
            files["camera2"] = {n: stat(where2[n]) if n in v.camera2.frames else None for n in names}
        per_view[v.name] = _digest({**base, "view": entry, "files": files})
    return InputHashes(rig=base["rig"], patterns=base["patterns"], settings=base["settings"], views=per_view,
                       scan=_digest({**base, "views": per_view}))


@dataclass(frozen=True)
class DoneCheck:
    """What an output folder already holds for a scan, view by view."""

    hashes: InputHashes
    """The inputs' hashes now."""
    kept: dict[str, dict] = field(default_factory=dict)
    """View name -> its entry of the earlier report: made from the same inputs, files whole."""
    redo: dict[str, str] = field(default_factory=dict)
    """View name -> why it must be (re)done."""
    report: dict | None = None
    """The earlier report (None when there is none or it cannot be read)."""
    finished: bool = True
    """Whether the earlier run wrote its final report (with ``totals``): a run killed
    after its last view's report but before the final one left every view whole yet
    the report unfinished; a resumed run keeps the views and finishes the report."""

    @property
    def done(self) -> bool:
        """True when every view asked for is done and the earlier report is finished."""
        return not self.redo and self.finished


def check_done(scan: Scan, out_dir: str | os.PathLike, *, settings, views: list[str] | None = None,
               stat: Callable[[Path], list | None] | None = None) -> DoneCheck:
    """Which views of ``scan`` are done in ``out_dir`` (``report.json`` + PLYs), and why the others are not.

    Args:
        scan: a loaded scan.
        out_dir: the reconstruction folder.
        settings: the resolved settings of the run that asks.
        views: names of the views asked for (default: all).
        stat: how a frame file's size and time are found (see :func:`hash_inputs`).

    Returns:
        A :class:`DoneCheck`; ``.done`` is True when nothing needs to be redone.
    """
    hashes = hash_inputs(scan, settings, views=views, stat=stat)
    names = [v.name for v in scan.views if v.name in hashes.views]
    out = Path(out_dir)
    rpath = out / "report.json"
    if not rpath.exists():
        return DoneCheck(hashes, redo={n: "no earlier result" for n in names})
    try:
        old = read_json(rpath)
    except FormatError as e:
        return DoneCheck(hashes, redo={n: f"the earlier report cannot be read ({e.message})" for n in names})
    why_all = None
    if old.get("format") != REPORT_FORMAT:
        why_all = f"the earlier report is of format {old.get('format')!r}, not {REPORT_FORMAT!r}"
    inputs = old.get("inputs")
    if why_all is None and (not isinstance(inputs, dict) or inputs.get("recipe") != HASH_RECIPE):
        why_all = "the earlier report records no input hashes of this version (made by an older ringscan)"
    if why_all is not None:
        return DoneCheck(hashes, redo={n: why_all for n in names}, report=old)
    changed = [what for what in ("settings", "rig", "patterns") if inputs.get(what) != getattr(hashes, what)]
    entries = {}
    for e in old.get("views", []) if isinstance(old.get("views"), list) else []:
        if isinstance(e, dict) and isinstance(e.get("name"), str):
            entries[e["name"]] = e
    kept, redo = {}, {}
    for n in names:
        e = entries.get(n)
        if e is None:
            redo[n] = "not done before"
        elif e.get("inputs_hash") != hashes.views[n]:
            redo[n] = (" and ".join(changed) + " changed") if changed else \
                "its frames or its entry in scan.json changed"
        else:
            why = _check_files(out, n, e)
            if why is None:
                kept[n] = e
            else:
                redo[n] = why
    return DoneCheck(hashes, kept=kept, redo=redo, report=old, finished=isinstance(old.get("totals"), dict))


def _check_files(out: Path, name: str, entry: dict) -> str | None:
    ply = f"{name}.ply"
    if entry.get("ply") != ply:
        return f"the report names {entry.get('ply')!r} as its cloud, not {ply!r}"
    try:
        n = check_ply(out / ply)
    except FormatError as e:
        return f"{ply}: {e.message}"
    if n != entry.get("points"):
        return f"{ply} holds {n} points, the report says {entry.get('points')}"
    return None
