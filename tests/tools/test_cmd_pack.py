"""``ringscan pack`` / ``unpack``, and packed scans through simulate, reconstruct, batch and evaluate."""

import shutil

import numpy as np

from ringscan.pipeline.formats.patterns import parse_patterns
from ringscan.pipeline.formats.scan import load_scan, read_view_frames
from ringscan.pipeline.simulate.scan import simulate_scan
from ringscan.tools.cli import main
from tests.support.tiny_scan import TINY_PATTERNS, simulate_tiny_scan, tiny_rig


def _plys(folder):
    return {p.relative_to(folder).as_posix(): p.read_bytes() for p in sorted(folder.rglob("*.ply"))}


def test_packed_scans_reconstruct_to_the_same_bytes(tmp_path, capsys):
    root = tmp_path / "scans"
    png = simulate_tiny_scan(root / "a_png", turntable_deg=(0.0, 90.0))
    # the virtual rig writing a store directly, and `ringscan pack` of a copy of the PNG scan
    packed = simulate_scan(root / "b_sim", scene="sphere", size_mm=40.0, rig=tiny_rig(),
                           patterns=parse_patterns(TINY_PATTERNS), turntable_deg=(0.0, 90.0), progress=False,
                           image_format="packed")
    assert [v.packed for v in packed.views] == ["view_000/frames.zarr", "view_001/frames.zarr"]
    shutil.copytree(root / "a_png", root / "c_pack")
    assert main(["pack", str(root / "c_pack")]) == 0
    assert "2 view(s) packed" in capsys.readouterr().out
    for name in ("b_sim", "c_pack"):
        s = load_scan(root / name)
        for v, pv in zip(s.views, png.views):
            assert np.array_equal(read_view_frames(s, v), read_view_frames(png, pv))
    # one process per scan, and a batch on worker processes
    for name in ("a_png", "b_sim", "c_pack"):
        assert main(["reconstruct", str(root / name), "--out", str(tmp_path / "rec" / name), "--device", "cpu",
                     "--no-progress"]) == 0
    assert main(["batch", str(root), "--out", str(tmp_path / "batch"), "--workers", "1", "--device", "cpu"]) == 0
    ref = _plys(tmp_path / "rec" / "a_png")
    assert len(ref) == 2 and all(len(b) > 1000 for b in ref.values())
    for name in ("b_sim", "c_pack"):
        assert _plys(tmp_path / "rec" / name) == ref
    for name in ("a_png", "b_sim", "c_pack"):
        assert _plys(tmp_path / "batch" / name) == ref
    # evaluate reads the packed scan (and its truth beside the store) as it reads the PNG scan
    for name in ("a_png", "b_sim"):
        assert main(["evaluate", str(tmp_path / "rec" / name), "--truth", str(root / name),
                     "--json", str(tmp_path / f"ev_{name}.json")]) == 0
    assert (tmp_path / "ev_a_png.json").read_text() == (tmp_path / "ev_b_sim.json").read_text()


def test_pack_a_root_names_a_bad_frame_in_one_line_and_unpack_restores(tmp_path, capsys):
    root = tmp_path / "root"
    good = simulate_tiny_scan(root / "good")
    simulate_tiny_scan(root / "bad")
    frames_before = read_view_frames(good, good.views[0])
    broken = root / "bad" / "view_000" / "gray_1.png"
    broken.write_bytes(b"not a png")
    assert main(["pack", str(root)]) == 1
    out, err = capsys.readouterr()
    assert err.count("\n") == 1 and str(broken) in err and "Traceback" not in err
    assert "good: 1 view(s) packed" in out
    assert load_scan(root / "bad").views[0].packed is None  # nothing of the bad scan changed
    assert not (root / "bad" / "view_000" / "frames.zarr").exists()
    assert load_scan(root / "good").views[0].packed
    # a damaged store: reconstruct names the chunk in one line, writes no PLY
    chunk = root / "good" / "view_000" / "frames.zarr" / "c" / "3" / "0" / "0"
    intact = chunk.read_bytes()
    chunk.write_bytes(intact[:-5] + bytes([intact[-5] ^ 1]) + intact[-4:])
    assert main(["reconstruct", str(root / "good"), "--out", str(tmp_path / "rec"), "--device", "cpu",
                 "--no-progress"]) == 1  # a damaged input: a failed run (docs/cli.md)
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and str(chunk) in err and "CRC32C" in err
    assert not list((tmp_path / "rec").glob("*.ply"))
    # a chunk missing or cut short: refused from the files' sizes before anything is written
    for damage, why in ((lambda: chunk.unlink(), "frame missing"), (lambda: chunk.write_bytes(intact[:9]),
                                                                   "frame chunk of 9 bytes")):
        damage()
        rec = tmp_path / f"rec_{why.split()[-1]}"
        assert main(["reconstruct", str(root / "good"), "--out", str(rec), "--device", "cpu", "--no-progress"]) == 1
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and str(chunk) in err and why in err
        assert not rec.exists() or not any(rec.iterdir())
    chunk.write_bytes(intact)
    assert main(["unpack", str(root / "good"), "--image-format", "tiff"]) == 0
    s = load_scan(root / "good")
    assert s.views[0].packed is None and s.views[0].frames["white"] == "view_000/white.tiff"
    assert np.array_equal(read_view_frames(s, s.views[0]), frames_before)
    assert main(["pack", str(tmp_path / "nothing")]) == 1  # an input that is not there: a failed run
    assert "not a folder" in capsys.readouterr().err


def test_pack_and_unpack_a_root_on_worker_processes(tmp_path, capsys):
    root = tmp_path / "root"
    frames = {}
    for name in ("a", "b", "c"):
        s = simulate_tiny_scan(root / name)
        frames[name] = read_view_frames(s, s.views[0])
    (root / "b" / "view_000" / "white.png").write_bytes(b"broken")
    assert main(["pack", str(root), "--workers", "2"]) == 1
    out, err = capsys.readouterr()
    assert sorted(line.split(":")[0] for line in out.splitlines()) == [str(root / "a"), str(root / "c")]
    assert err.count("\n") == 1 and str(root / "b" / "view_000" / "white.png") in err
    assert main(["unpack", str(root), "--workers", "2"]) == 0
    for name in ("a", "c"):
        s = load_scan(root / name)
        assert s.views[0].packed is None and np.array_equal(read_view_frames(s, s.views[0]), frames[name])
    assert main(["pack", str(root), "--workers", "0"]) == 2
    assert "--workers" in capsys.readouterr().err


def test_a_two_camera_scan_packs_and_unpacks_to_the_same_reconstruction(tmp_path, capsys):
    from ringscan.pipeline.formats.scan import as_camera2
    from tests.support.two_camera_scan import simulate_two_camera_scan

    folder = tmp_path / "scan"
    png = simulate_two_camera_scan(folder)
    frames2 = read_view_frames(as_camera2(png), png.views[0].camera2)

    def rec(name):
        assert main(["reconstruct", str(folder), "--out", str(tmp_path / name), "--rays", "all", "--device", "cpu",
                     "--no-progress"]) == 0
        return _plys(tmp_path / name)

    ref = rec("png")
    assert len(ref) == 1 and len(ref["view_000.ply"]) > 1000
    assert main(["pack", str(folder)]) == 0
    assert "1 view(s) packed" in capsys.readouterr().out
    s = load_scan(folder)
    v = s.views[0]
    assert (v.packed, v.camera2.packed) == ("view_000/frames.zarr", "view_000/cam2/frames.zarr")
    assert not list(folder.glob("view_000/**/*.png"))
    assert np.array_equal(read_view_frames(as_camera2(s), v.camera2), frames2)
    assert rec("packed") == ref
    assert main(["unpack", str(folder)]) == 0
    s = load_scan(folder)
    assert s.views[0].camera2.frames["white"] == "view_000/cam2/white.png" and not list(folder.rglob("frames.zarr"))
    assert rec("unpacked") == ref


def test_a_zarr_json_nested_too_deeply_is_named_by_reconstruct_unpack_and_batch(tmp_path, capsys):
    """A zarr.json of 100000 `[`: before, a RecursionError traceback (reconstruct, unpack) and
    `FAILED: RecursionError` without the file (batch)."""
    from ringscan.pipeline.formats.packing import pack_scan
    from tests.support.noise_scan import noise_scan

    folder = tmp_path / "root" / "scan"
    noise_scan(folder, views=1)  # 40x30 frames of noise: nothing here is reconstructed
    pack_scan(folder)
    meta = folder / "view_0" / "frames.zarr" / "zarr.json"
    meta.write_text("[" * 100000)
    capsys.readouterr()
    want = f"{meta}: not valid JSON (nested too deeply)"
    assert main(["reconstruct", str(folder), "--out", str(tmp_path / "rec"), "--device", "cpu"]) == 1
    assert capsys.readouterr().err.strip() == f"ringscan reconstruct: error: {want}"
    assert main(["unpack", str(folder)]) == 1
    assert capsys.readouterr().err.strip() == f"{folder}: failed: {want}"
    assert main(["batch", str(tmp_path / "root"), "--out", str(tmp_path / "b"), "--workers", "0", "--device", "cpu",
                 "--no-progress"]) == 1
    out = capsys.readouterr().out
    assert f"FAILED: {want}" in out, out
    assert not (tmp_path / "rec").exists() and not list((folder / "view_0").glob("*.png"))


def test_store_metadata_that_does_not_fit_is_refused_before_the_first_ply(tmp_path, capsys):
    """Frame names reordered, or a data type other than the chunks hold, in view_1's zarr.json: before, refused
    only when view_1 was read, after view_0's PLY was written."""
    import json

    from ringscan.pipeline.formats.packing import pack_scan
    from tests.support.noise_scan import noise_scan

    folder = tmp_path / "scan"
    noise_scan(folder, views=2)
    pack_scan(folder)
    meta = folder / "view_1" / "frames.zarr" / "zarr.json"
    good = json.loads(meta.read_text())
    names = good["attributes"]["ringscan"]["frames"]
    for edit, why in ((lambda d: d["attributes"]["ringscan"].update(frames=names[::-1]),
                       f"{meta}: frames {', '.join(names[::-1])} do not match scan.json's list for view_1"),
                      (lambda d: d.update(data_type="uint16"),
                       f"{meta.parent / 'c' / '0' / '0' / '0'}: frame chunk holds 1200 bytes, not one 40x30 uint16 "
                       "frame")):
        d = json.loads(json.dumps(good))
        edit(d)
        d["codecs"][1]["configuration"]["typesize"] = 2 if d["data_type"] == "uint16" else 1
        meta.write_text(json.dumps(d))
        out = tmp_path / "rec"
        assert main(["reconstruct", str(folder), "--out", str(out), "--device", "cpu", "--no-progress"]) == 1
        err = capsys.readouterr().err.strip()
        assert err.startswith(f"ringscan reconstruct: error: {why}"), err
        assert not out.exists()


def test_pack_says_which_scans_it_passed_over_and_unpack_goes_on_past_a_failed_scan(tmp_path, capsys, monkeypatch):
    """A scan nested in a view folder: before, `pack TREE` skipped it without a word. A scan whose unpack raises
    an exception of a library (not ringscan's own): before, `unpack ROOT` stopped there."""
    from ringscan.pipeline.formats import packing
    from ringscan.tools import cmd_unpack
    from tests.support.noise_scan import noise_scan

    root = tmp_path / "root"
    for name in ("a", "b"):
        noise_scan(root / name, views=1)
    noise_scan(root / "a" / "view_0" / "inner", views=1)
    assert main(["pack", str(root)]) == 0
    out = capsys.readouterr().out
    assert f"{root / 'a'}: 1 view(s) packed" in out and f"{root / 'b'}: 1 view(s) packed" in out
    assert (f"not searched: {root / 'a' / 'view_0' / 'inner'}: a scan folder inside the scan folder {root / 'a'}: "
            "not processed") in out, out

    def unpack(folder, **kw):
        if folder.name == "a":
            raise RuntimeError("numcodecs: something went wrong")
        return packing.unpack_scan(folder, **kw)

    monkeypatch.setattr(cmd_unpack, "unpack_scan", unpack)
    assert main(["unpack", str(root)]) == 1
    out, err = capsys.readouterr()
    assert err.strip() == f"{root / 'a'}: failed: RuntimeError: numcodecs: something went wrong"
    assert f"{root / 'b'}: 1 view(s) unpacked" in out



def test_pack_workers_end_when_their_parent_is_killed(tmp_path):
    """`pack ROOT --workers 2` with its parent SIGKILLed: before, the workers and the resource tracker ran on for
    more than 60 s. Killed while the workers start (the watchdog is their pool initializer's)."""
    import os
    import signal
    import subprocess
    import sys
    import time

    from tests.support.noise_scan import noise_scan
    from tests.support.processes import children, running

    for name in "abcdef":
        noise_scan(tmp_path / "root" / name, views=1)
    proc = subprocess.Popen([sys.executable, "-m", "ringscan.tools.cli", "pack", str(tmp_path / "root"),
                             "--workers", "2"], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    deadline = time.monotonic() + 60
    while len(kids := children(proc.pid)) < 3 and proc.poll() is None and time.monotonic() < deadline:
        time.sleep(0.02)  # two workers and the resource tracker
    assert proc.poll() is None, "pack ended before it could be killed"
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait()
    deadline = time.monotonic() + 10
    while any(running(k) for k in kids) and time.monotonic() < deadline:
        time.sleep(0.1)
    assert not any(running(k) for k in kids)
