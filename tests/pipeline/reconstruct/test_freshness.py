"""A result counts as done only when it was made from the same inputs with the same
settings and its files are whole: ``reconstruct --resume`` and ``batch`` redo
everything else and say why."""

from __future__ import annotations

import dataclasses
import json
import os
import shutil
import signal
import stat
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from ringscan.pipeline.batch import batch_reconstruct
from ringscan.pipeline.formats.atomic import read_json
from ringscan.pipeline.formats.errors import FormatError
from ringscan.pipeline.formats.images import read_image, write_image
from ringscan.pipeline.formats.patterns import parse_patterns
from ringscan.pipeline.formats.ply import read_ply
from ringscan.pipeline.formats.scan import Scan, View, load_scan, read_view_frames
from ringscan.pipeline.reconstruct.freshness import check_done, hash_inputs
from ringscan.pipeline.reconstruct.scan import reconstruct_scan
from ringscan.pipeline.reconstruct.settings import ReconstructSettings
from ringscan.pipeline.reconstruct.view import explain_no_points
from ringscan.tools.cli import main
from tests.support.tiny_scan import simulate_tiny_scan, tiny_rig

OTHER = ReconstructSettings(min_confidence=0.5)


@pytest.fixture(scope="module")
def tiny_scan_src(tmp_path_factory):
    folder = tmp_path_factory.mktemp("tiny") / "scan"
    simulate_tiny_scan(folder, turntable_deg=(0.0, 120.0))
    return folder


@pytest.fixture
def scan(tiny_scan_src, tmp_path):
    """A fresh copy of the tiny scan (tests change its files)."""
    dst = tmp_path / "scan"
    shutil.copytree(tiny_scan_src, dst)
    return load_scan(dst)


def _points(folder, view):
    p = read_ply(folder / f"{view}.ply")
    return np.stack([p["x"], p["y"], p["z"]], 1)


def _consistent(out):
    """The report tells the truth about the PLYs next to it."""
    rep = read_json(out / "report.json")
    for v in rep["views"]:
        assert len(_points(out, v["name"])) == v["points"], v["name"]
    return rep


def test_resume_with_other_settings_redoes_every_view_and_says_why(scan, tmp_path):
    out = tmp_path / "rec"
    reconstruct_scan(scan, out, device="cpu", progress=False)
    rep = reconstruct_scan(scan, out, settings=OTHER, device="cpu", resume=True, progress=False)
    assert rep["resume"] == {"kept": [], "redone": {"view_000": "settings changed", "view_001": "settings changed"}}
    fresh = tmp_path / "fresh"
    reconstruct_scan(scan, fresh, settings=OTHER, device="cpu", progress=False)
    for v in ("view_000", "view_001"):  # the points are those of the new settings
        assert np.array_equal(_points(out, v), _points(fresh, v))
    assert _consistent(out)["settings"]["min_confidence"] == 0.5
    assert read_json(out / "settings.json")["min_confidence"] == 0.5


def test_resume_keeps_views_made_from_the_same_inputs(scan, tmp_path):
    out = tmp_path / "rec"
    reconstruct_scan(scan, out, device="cpu", progress=False)
    before = {p.name: p.stat().st_mtime_ns for p in out.glob("*.ply")}
    rep = reconstruct_scan(scan, out, settings=ReconstructSettings(threads=1), device="cpu", resume=True,
                           progress=False)
    assert rep["resume"] == {"kept": ["view_000", "view_001"], "redone": {}}
    assert {p.name: p.stat().st_mtime_ns for p in out.glob("*.ply")} == before
    assert check_done(scan, out, settings=ReconstructSettings()).done


def test_a_report_left_unfinished_is_finished_without_redoing_views(scan, tmp_path):
    """Killed after the last view's report but before the final one (no totals): every
    view is whole, yet the scan is not done; a resumed run keeps the views and writes
    the report a finished run writes (a batch worker killed with its pool did this)."""
    out = tmp_path / "rec"
    full = reconstruct_scan(scan, out, device="cpu", progress=False)
    rep = read_json(out / "report.json")
    del rep["totals"], rep["time_s"]
    (out / "report.json").write_text(json.dumps(rep))
    before = {p.name: p.stat().st_mtime_ns for p in out.glob("*.ply")}
    check = check_done(scan, out, settings=ReconstructSettings())
    assert not check.done and not check.finished and set(check.kept) == {"view_000", "view_001"} and not check.redo
    from ringscan.pipeline.batch.discover import plan_scan

    plan = plan_scan(scan.folder, "scan", out, settings=ReconstructSettings())  # what --dry-run says
    assert (plan.action, plan.why) == ("run", "incomplete") and "no view is redone" in plan.detail
    again = reconstruct_scan(scan, out, device="cpu", resume=True, progress=False)
    assert again["resume"] == {"kept": ["view_000", "view_001"], "redone": {}}
    assert again["totals"] == full["totals"]
    assert {p.name: p.stat().st_mtime_ns for p in out.glob("*.ply")} == before
    assert check_done(scan, out, settings=ReconstructSettings()).done


@pytest.mark.parametrize("damage", ["empty", "truncated", "missing"])
def test_a_damaged_ply_is_redone(scan, tmp_path, damage):
    out = tmp_path / "rec"
    reconstruct_scan(scan, out, device="cpu", progress=False)
    ply = out / "view_001.ply"
    whole = ply.read_bytes()
    if damage == "missing":
        ply.unlink()
    else:
        ply.write_bytes(b"" if damage == "empty" else whole[: len(whole) // 2 + 3])
    check = check_done(scan, out, settings=ReconstructSettings())
    assert not check.done and list(check.kept) == ["view_000"]
    assert check.redo["view_001"].startswith("view_001.ply: ")
    rep = reconstruct_scan(scan, out, device="cpu", resume=True, progress=False)
    assert rep["resume"]["kept"] == ["view_000"] and "view_001" in rep["resume"]["redone"]
    assert ply.read_bytes() == whole
    _consistent(out)


def test_a_changed_frame_redoes_its_view_only(scan, tmp_path):
    out = tmp_path / "rec"
    reconstruct_scan(scan, out, device="cpu", progress=False)
    frame = scan.frame_path(scan.views[0], "gray_2")
    img = read_image(frame)
    write_image(frame, np.ascontiguousarray(img[:, ::-1]))  # another picture of the same size
    check = check_done(scan, out, settings=ReconstructSettings())
    assert check.redo == {"view_000": "its frames or its entry in scan.json changed"}
    rep = reconstruct_scan(scan, out, device="cpu", resume=True, progress=False)
    assert rep["resume"]["kept"] == ["view_001"]
    _consistent(out)


def test_a_changed_frame_of_a_packed_view_redoes_its_view_only(scan, tmp_path):
    from ringscan.pipeline.formats.frame_store import open_store, write_frame
    from ringscan.pipeline.formats.packing import pack_scan

    pack_scan(scan.folder)
    scan = load_scan(scan.folder)
    out = tmp_path / "rec"
    reconstruct_scan(scan, out, device="cpu", progress=False)
    assert check_done(scan, out, settings=ReconstructSettings()).done
    info = open_store(scan.folder / scan.views[1].packed)
    img = read_view_frames(scan, scan.views[1], ["gray_2"])[0]
    write_frame(info, "gray_2", np.ascontiguousarray(img[:, ::-1]))  # one chunk rewritten in place
    check = check_done(scan, out, settings=ReconstructSettings())
    assert check.redo == {"view_001": "its frames or its entry in scan.json changed"}


def test_a_changed_rig_redoes_every_view(scan, tmp_path):
    out = tmp_path / "rec"
    reconstruct_scan(scan, out, device="cpu", progress=False)
    d = json.loads(scan.path.read_text())
    d["rig"]["volume"]["z_max"] = 60.0
    scan.path.write_text(json.dumps(d))
    check = check_done(load_scan(scan.folder), out, settings=ReconstructSettings())
    assert check.redo == {"view_000": "rig changed", "view_001": "rig changed"}


def test_a_report_without_hashes_is_redone(scan, tmp_path):
    out = tmp_path / "rec"
    reconstruct_scan(scan, out, device="cpu", progress=False)
    rep = read_json(out / "report.json")
    del rep["inputs"]
    (out / "report.json").write_text(json.dumps(rep))
    check = check_done(scan, out, settings=ReconstructSettings())
    assert set(check.redo) == {"view_000", "view_001"} and "older ringscan" in check.redo["view_000"]


def test_hash_inputs():
    rig = tiny_rig()
    spec = parse_patterns({"codec": "gray-rings", "width": 256, "height": 192, "center": [127.5, 95.5],
                           "rho0": 4.0, "pitch": 3.0, "bits": 3})
    s = Scan(folder=Path("/nonexistent"), rig=rig, patterns=spec,
             views=(View("a", 0.0, {}), View("b", 90.0, {})))
    h = hash_inputs(s, ReconstructSettings())
    assert h == hash_inputs(s, ReconstructSettings(threads=3))  # threads do not change a result
    assert h.settings != hash_inputs(s, OTHER).settings and h.scan != hash_inputs(s, OTHER).scan
    assert h.views["a"] != h.views["b"]
    s2 = dataclasses.replace(s, views=(View("a", 0.0, {}), View("b", 91.0, {})))
    h2 = hash_inputs(s2, ReconstructSettings())
    assert h2.views["a"] == h.views["a"] and h2.views["b"] != h.views["b"]
    assert list(hash_inputs(s, ReconstructSettings(), views=["b"]).views) == ["b"]


# ----------------------------------------------------------------------------- batch


def test_batch_redoes_a_scan_made_with_other_settings(scan, tmp_path):
    root = scan.folder.parent
    out = tmp_path / "out"
    rep = batch_reconstruct(root, out, device="cpu", progress=False)
    assert [s["status"] for s in rep["scans"]] == ["done"]
    rep = batch_reconstruct(root, out, device="cpu", progress=False)
    assert [s["status"] for s in rep["scans"]] == ["skipped (already done)"]
    rep = batch_reconstruct(root, out, settings=OTHER, device="cpu", progress=False)
    s = rep["scans"][0]
    assert s["status"] == "done" and s["redone"] == {"view_000": "settings changed", "view_001": "settings changed"}
    assert _consistent(out / "scan")["settings"]["min_confidence"] == 0.5
    (out / "scan" / "view_000.ply").write_bytes(b"")
    s = batch_reconstruct(root, out, settings=OTHER, device="cpu", progress=False)["scans"][0]
    assert s["status"] == "done" and list(s["redone"]) == ["view_000"]
    assert "empty file" in s["redone"]["view_000"]


# ----------------------------------------------------------------------------- files and folders


def _leave_a_temporary(folder, name):
    """A writer killed in the middle of an atomic write (its temporary file stays)."""
    code = ("import os, signal; from pathlib import Path; from ringscan.pipeline.formats.atomic import atomic_path\n"
            f"with atomic_path(Path({str(folder)!r}) / {name!r}) as tmp:\n"
            "    tmp.write_bytes(b'half')\n    os.kill(os.getpid(), signal.SIGKILL)\n")
    assert subprocess.run([sys.executable, "-c", code]).returncode == -signal.SIGKILL
    left = [p for p in folder.iterdir() if p.name.startswith(f".{name}.")]
    assert len(left) == 1
    return left[0]


def test_reconstruct_and_batch_remove_leftover_temporaries(scan, tmp_path):
    out = tmp_path / "rec"
    out.mkdir()
    left = _leave_a_temporary(out, "view_000.ply")
    reconstruct_scan(scan, out, device="cpu", progress=False)
    assert not left.exists()
    batch_out = tmp_path / "batch"
    batch_out.mkdir()
    left = _leave_a_temporary(batch_out, "batch_report.json")
    batch_reconstruct(scan.folder.parent, batch_out, device="cpu", progress=False)
    assert not left.exists()


@pytest.mark.parametrize("mask", [0o022, 0o002])
def test_outputs_are_readable_like_any_other_file(scan, tmp_path, mask):
    old = os.umask(mask)
    try:
        out = tmp_path / "rec"
        reconstruct_scan(scan, out, device="cpu", progress=False)
        files = sorted(p.name for p in out.iterdir())
        assert files == ["report.json", "settings.json", "view_000.ply", "view_001.ply"]
        for p in out.iterdir():
            assert stat.S_IMODE(p.stat().st_mode) == 0o666 & ~mask, p.name
    finally:
        os.umask(old)


def test_an_output_folder_that_would_overwrite_an_input_is_refused(scan):
    d = json.loads(scan.path.read_text())
    (scan.folder / "settings.json").write_text(json.dumps(d["rig"]))  # the rig in a file named settings.json
    d["rig"] = "settings.json"
    scan.path.write_text(json.dumps(d))
    rig_bytes = (scan.folder / "settings.json").read_bytes()
    with pytest.raises(FormatError, match="settings.json: writing it would overwrite the input"):
        reconstruct_scan(scan.folder, scan.folder, device="cpu", progress=False)
    assert (scan.folder / "settings.json").read_bytes() == rig_bytes
    assert not (scan.folder / "report.json").exists()


def test_a_view_named_dotdot_writes_nothing(scan, tmp_path):
    bad = dataclasses.replace(scan, views=(dataclasses.replace(scan.views[0], name=".."),))
    with pytest.raises(FormatError, match="'..' is not a folder-safe name"):
        reconstruct_scan(bad, tmp_path / "rec", device="cpu", progress=False)
    assert not (tmp_path / "...ply").exists() and not (tmp_path / "rec").exists()


# ----------------------------------------------------------------------------- no points


@pytest.mark.parametrize("level,why", [(0, "everything is dark"), (255, "everything is saturated")])
def test_frames_without_contrast_say_so_and_fail(scan, tmp_path, capsys, level, why):
    for v in scan.views:
        for n in v.frames:
            write_image(scan.frame_path(v, n), np.full((128, 160), level, np.uint8))
    out = tmp_path / "rec"
    rc = main(["reconstruct", str(scan.folder), "--out", str(out), "--device", "cpu", "--no-progress"])
    err = capsys.readouterr().err
    assert rc == 1
    assert "no view of" in err and "gave any point: no ring found: no contrast between the white and black " \
                                  "frames" in err and why in err
    rep = read_json(out / "report.json")
    assert all("no contrast" in v["no_points"] for v in rep["views"])
    s = batch_reconstruct(scan.folder.parent, tmp_path / "batch", device="cpu", progress=False)["scans"][0]
    assert s["status"] == "failed" and "no view gave any point: no ring found: no contrast" in s["error"]
    # rerun: done (same inputs) but still no point, still a failure
    s = batch_reconstruct(scan.folder.parent, tmp_path / "batch", device="cpu", progress=False)["scans"][0]
    assert s["status"] == "failed" and "no contrast" in s["error"]


def test_one_dark_view_is_a_warning_not_a_failure(scan, tmp_path, caplog):
    for n in scan.views[1].frames:
        write_image(scan.frame_path(scan.views[1], n), np.zeros((128, 160), np.uint8))
    rc = main(["reconstruct", str(scan.folder), "--out", str(tmp_path / "rec"), "--device", "cpu", "--no-progress"])
    assert rc == 0
    warned = [r.getMessage() for r in caplog.records if r.levelname == "WARNING"]
    assert len(warned) == 1 and "view_001" in warned[0] and "everything is dark" in warned[0]
    rep = read_json(tmp_path / "rec" / "report.json")
    assert rep["views"][0]["points"] > 0 and "no_points" not in rep["views"][0]
    assert "everything is dark" in rep["views"][1]["no_points"]


def test_explain_no_points_other_cases(scan):
    rings = dataclasses.replace(scan, patterns=parse_patterns(
        {"codec": "rings", "width": 256, "height": 192, "center": [127.5, 95.5], "rho0": 8.0, "pitch": 12.0,
         "count": 5, "line_width": 3.0}))
    grey = np.full((1, 128, 160), 90, np.uint8)
    assert "the rings frame has no contrast (grey levels 90 to 90" in explain_no_points(grey, rings, {})
    lines = grey.copy()
    lines[0, ::8] = 200
    why = explain_no_points(lines, rings, {"line_samples": 300, "pieces": 7, "samples": 0})
    assert why == ("no ring found: 300 line centres in 7 pieces, none labelled with a ring (see the labelling "
                   "counts in the report)")
    frames = np.zeros((14, 128, 160), np.uint8)
    frames[0] = 200  # white lit, black dark: contrast everywhere
    assert "none decodes to a ring band" in explain_no_points(frames, scan, {"pixels_decoded": 0})
    why = explain_no_points(frames, scan, {"pixels_decoded": 500, "samples": 40,
                                           "dropped": {"no_root": 0, "outside_volume": 40}})
    assert why == ("every one of the 40 ring samples was dropped (outside_volume 40): check the rig's calibration "
                   "and working volume")


def test_a_frame_whose_body_is_corrupt_stops_the_run_before_anything_is_written(tmp_path):
    """The frames' headers are checked before anything is written; a PNG cut short after a good
    header is found only when its view is read. In the first view to compute, it stops the run
    with the file and the problem, and the output folder holds nothing (settings.json goes with
    the first view's points)."""
    from ringscan.pipeline.reconstruct.scan import reconstruct_scan

    scan = simulate_tiny_scan(tmp_path / "scan")
    frame = scan.folder / scan.views[0].frames["gray_1"]
    data = frame.read_bytes()
    frame.write_bytes(data[: len(data) // 2])  # the header intact, the image data cut
    out = tmp_path / "rec"
    with pytest.raises(FormatError, match="gray_1.png: not a readable image"):
        reconstruct_scan(load_scan(scan.folder), out, progress=False)
    assert not out.exists() or [p.name for p in out.iterdir()] == []
