"""``ringscan batch``: every scan below a folder, failures listed, reruns resume."""

import pytest

from ringscan.pipeline.batch import batch_reconstruct, find_scans
from ringscan.pipeline.evaluate.metrics import evaluate_recon
from ringscan.pipeline.formats.atomic import read_json
from ringscan.pipeline.formats.errors import RingscanError
from ringscan.tools.cli import main
from tests.support.header_only import huge_png


def test_batch_reconstructs_every_scan_and_resumes(scan_root, tmp_path, monkeypatch):
    import os

    import warp as wp

    assert [p.relative_to(scan_root).as_posix() for p in find_scans(scan_root)] == ["a_sphere", "b/cube"]
    out = tmp_path / "out"
    # the default: one worker process per GPU, else per core; no GPU and one core counted: one worker to start
    monkeypatch.setattr(wp, "get_cuda_device_count", lambda: 0)
    monkeypatch.setattr(os, "cpu_count", lambda: 1)
    rep = batch_reconstruct(scan_root, out, progress=False)
    assert [s["status"] for s in rep["scans"]] == ["done", "done"]
    assert rep["workers"] == 1 and rep["totals"]["worker_start_s"]["workers"] == 1
    for rel in ("a_sphere", "b/cube"):
        ev = evaluate_recon(out / rel, scan_root / rel)
        # about 0.02 mm here; a point decoded on the wrong ring is off by about the rings' 1.8 mm spacing
        assert ev["all"]["median_mm"] < 0.1 and ev["all"]["frac_over_1mm"] < 0.01
    assert read_json(out / "batch_report.json")["scans"] == rep["scans"]
    assert all(s["cpu_s"] > 0 for s in rep["scans"])  # the workers' CPU seconds, per scan and per view
    assert rep["totals"]["cpu_per_view_s"] == pytest.approx(sum(s["cpu_s"] for s in rep["scans"])
                                                            / rep["totals"]["computed_views"])
    # the results came back between the start and the end (closing the workers, the final report after them)
    tot = rep["totals"]
    assert 0 < tot["first_result_s"] <= tot["last_result_s"] <= tot["wall_s"]
    ply = out / "a_sphere" / "view_000.ply"
    before = ply.stat().st_mtime_ns
    # the rerun in this process (no pool to start: the decision is the same process_scan's, wherever it runs)
    rep2 = batch_reconstruct(scan_root, out, workers=0, progress=False)
    assert [s["status"] for s in rep2["scans"]] == ["skipped (already done)"] * 2
    assert ply.stat().st_mtime_ns == before  # nothing redone
    assert rep2["totals"]["cpu_per_view_s"] == 0.0  # no view computed


def test_the_report_is_rewritten_after_the_first_scan_and_at_the_end_not_after_each(scan_root, tmp_path,
                                                                                    monkeypatch):
    import ringscan.pipeline.batch as batch

    written = []
    real = batch.write_json_to

    def count(path, report, options):
        written.append(len(report["scans"]))
        return real(path, report, options)

    monkeypatch.setattr(batch, "write_json_to", count)
    monkeypatch.setattr(batch, "REPORT_EVERY_S", 3600.0)
    rep = batch_reconstruct(scan_root, tmp_path / "out", workers=0, progress=False)
    assert written == [1, 2] and read_json(tmp_path / "out" / "batch_report.json")["scans"] == rep["scans"]
    assert "worker_start_s" not in rep["totals"]  # in-process (--workers 0): no worker was started
    written.clear()
    monkeypatch.setattr(batch, "REPORT_EVERY_S", 0.0)
    monkeypatch.setattr(batch, "REPORT_SHARE", 1e9)  # every scan
    batch_reconstruct(scan_root, tmp_path / "out2", workers=0, progress=False)
    assert written == [1, 2, 2]


def test_summarise_counts_cpu_of_the_scans_that_computed_views():
    from ringscan.pipeline.batch.report import summarise

    entries = [{"status": "done", "computed_views": 2, "cpu_s": 0.5, "times_s": {"read": 0.1}},
               {"status": "skipped (already done)", "computed_views": 0, "cpu_s": 0.25, "times_s": {}},
               {"status": "done", "computed_views": 1, "cpu_s": 0.25, "times_s": {"read": 0.2}},
               {"status": "failed", "error": "x", "cpu_s": 0.125}]
    tot = summarise(entries, wall_s=2.0)
    assert tot["computed_views"] == 3 and tot["views_per_s"] == 1.5
    assert tot["cpu_per_view_s"] == pytest.approx(0.75 / 3)
    assert tot["per_view_s"]["read"] == pytest.approx(0.1)


def test_batch_lists_a_broken_scan_and_goes_on(scan_root, tmp_path):
    import shutil

    root = tmp_path / "root"
    shutil.copytree(scan_root, root)
    frame = root / "a_sphere" / "view_000" / "white.png"
    frame.write_bytes(b"not a png")
    out = tmp_path / "out"
    # in this process (a scan's failure on the pool: test_on_the_pool_a_huge_frame_or_a_library_error_fails_...)
    rep = batch_reconstruct(root, out, workers=0, progress=False)
    status = {s["scan"]: s for s in rep["scans"]}
    assert status["a_sphere"]["status"] == "failed"
    assert "white.png" in status["a_sphere"]["error"] and "not a readable image" in status["a_sphere"]["error"]
    assert status["b/cube"]["status"] == "done"
    # the CLI says so and exits 1; the scan that worked is kept
    assert main(["batch", str(root), "--out", str(out), "--workers", "0", "--no-progress", "--device", "cpu"]) == 1
    assert (out / "b" / "cube" / "view_000.ply").is_file()


def test_batch_of_a_folder_without_scans(tmp_path):
    with pytest.raises(RingscanError, match="no scan.json"):
        batch_reconstruct(tmp_path, tmp_path / "out", progress=False)


def test_find_scans_follows_links_once(scan_root, tmp_path):
    root = tmp_path / "links"
    root.mkdir()
    (root / "one").symlink_to(scan_root / "a_sphere", target_is_directory=True)
    (root / "two").symlink_to(scan_root / "a_sphere", target_is_directory=True)
    (root / "all").symlink_to(scan_root, target_is_directory=True)
    found = [p.relative_to(root).as_posix() for p in find_scans(root)]
    assert found == ["all/b/cube", "one"] or found == ["all/a_sphere", "all/b/cube"]
    assert len(found) == 2  # a_sphere once, however many links reach it


def _copy(scan_root, tmp_path):
    import shutil

    root = tmp_path / "root"
    shutil.copytree(scan_root, root)
    return root


def test_link_loop_and_nested_scan_reported_by_the_batch(scan_root, tmp_path, capsys):
    import os
    import shutil

    root = _copy(scan_root, tmp_path)
    os.symlink("loop", root / "b" / "loop")
    shutil.copytree(scan_root / "a_sphere", root / "a_sphere" / "nested")
    out = tmp_path / "out"
    rc = main(["batch", str(root), "--out", str(out), "--workers", "0", "--no-progress", "--device", "cpu"])
    text = capsys.readouterr().out
    assert rc == 0
    rep = read_json(out / "batch_report.json")
    assert [s["scan"] for s in rep["scans"]] == ["a_sphere", "b/cube"]  # the loop hides b/cube no more
    assert [s["path"] for s in rep["not_searched"]] == [str(root / "a_sphere" / "nested"), str(root / "b" / "loop")]
    assert f"not searched: {root / 'b' / 'loop'}: cannot follow this link: too many levels of symbolic links" in text
    assert f"not searched: {root / 'a_sphere' / 'nested'}: a scan folder inside the scan folder" in text


def test_root_given_through_dot_dot_writes_inside_out(scan_root, tmp_path):
    out = tmp_path / "x" / "inner"
    rep = batch_reconstruct(f"{scan_root / 'a_sphere' / 'view_000'}/..", out, workers=0, device="cpu",
                            progress=False)
    assert [s["scan"] for s in rep["scans"]] == ["a_sphere"]
    assert sorted(p.name for p in (tmp_path / "x").iterdir()) == ["inner"]  # nothing written above OUT
    assert (out / "a_sphere" / "view_000.ply").is_file() and (out / "batch_report.json").is_file()


def test_a_huge_frame_fails_its_scan_alone(scan_root, tmp_path):
    """A 60000x60000 PNG (a few bytes on disk) as a frame: refused before decoding, that scan fails, named;
    the other is done and in the report; a rerun does the same (before: a cv2.error aborted the whole batch)."""
    root = _copy(scan_root, tmp_path)
    frame = root / "b" / "cube" / "view_000" / "gray_1.png"
    huge_png(frame)
    out = tmp_path / "out"
    for _ in range(2):
        rep = batch_reconstruct(root, out, workers=0, device="cpu", progress=False)
        status = {s["scan"]: s for s in rep["scans"]}
        assert status["b/cube"]["status"] == "failed"
        assert status["b/cube"]["error"].startswith(f"{frame}: image is 60000x60000 (3600 megapixels): larger than")
        assert status["a_sphere"]["status"] in ("done", "skipped (already done)")
        assert read_json(out / "batch_report.json")["scans"] == rep["scans"]


def test_a_library_exception_fails_its_scan_alone(scan_root, tmp_path, monkeypatch):
    """Any exception of one scan (here OpenCV's own cv2.error, raised as the scan starts) fails that scan alone,
    its type named (before: it aborted the batch, and the report lacked the scans already done)."""
    from ringscan.pipeline.batch.worker import RAISE_ENV

    monkeypatch.setenv(RAISE_ENV, "a_sphere")
    rep = batch_reconstruct(scan_root, tmp_path / "out", workers=0, device="cpu", progress=False)
    status = {s["scan"]: s for s in rep["scans"]}
    assert status["b/cube"]["status"] == "done"
    assert status["a_sphere"]["status"] == "failed"
    assert status["a_sphere"]["error"] == f"cv2.error: {RAISE_ENV}: OpenCV's own exception, raised on purpose"
    assert read_json(tmp_path / "out" / "batch_report.json")["scans"] == rep["scans"]


def test_on_the_pool_a_huge_frame_or_a_library_error_fails_its_scan_alone(scan_root, tmp_path, monkeypatch):
    """The two faults above in one batch on a worker pool (one worker: its start is most of this test's time):
    each fails its own scan, named, in the worker (before: the exception left the worker and aborted the
    batch); the third scan is done."""
    import shutil

    from ringscan.pipeline.batch.worker import RAISE_ENV

    root = _copy(scan_root, tmp_path)
    shutil.copytree(scan_root / "a_sphere", root / "c_raises")
    frame = root / "b" / "cube" / "view_000" / "gray_1.png"
    huge_png(frame)
    monkeypatch.setenv(RAISE_ENV, "c_raises")  # spawned workers take the environment
    rep = batch_reconstruct(root, tmp_path / "out", workers=1, device="cpu", progress=False)
    status = {s["scan"]: s for s in rep["scans"]}
    assert rep["totals"]["worker_start_s"]["workers"] == 1  # the scans ran on the pool
    assert status["a_sphere"]["status"] == "done"
    assert status["b/cube"]["status"] == "failed"
    assert status["b/cube"]["error"].startswith(f"{frame}: image is 60000x60000 (3600 megapixels): larger than")
    assert status["c_raises"]["status"] == "failed"
    assert status["c_raises"]["error"] == f"cv2.error: {RAISE_ENV}: OpenCV's own exception, raised on purpose"
    assert read_json(tmp_path / "out" / "batch_report.json")["scans"] == rep["scans"]


def test_one_run_at_a_time_on_an_output_folder(scan_root, tmp_path, capsys):
    """A second batch, reconstruct or import into a folder that a live run holds is refused with one line;
    a lock left by a dead process is taken over."""
    import subprocess
    import sys

    from ringscan.pipeline.formats.atomic import LOCK_NAME

    out = tmp_path / "out"
    out.mkdir()
    holder = subprocess.Popen([sys.executable, "-c", "import sys, time\n"
                               "from ringscan.pipeline.formats.atomic import lock_folder\n"
                               f"with lock_folder({str(out)!r}, what='batch'):\n"
                               "    print('held', flush=True); time.sleep(60)"], stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == "held"
        for argv in (["batch", str(scan_root), "--out", str(out), "--workers", "0"],
                     ["reconstruct", str(scan_root / "a_sphere"), "--out", str(out)]):
            rc = main([*argv, "--no-progress", "--device", "cpu"])
            err = capsys.readouterr().err.strip()
            assert rc == 1, err  # the output folder is busy: the run's input, not its usage
            assert err == (f"ringscan {argv[0]}: error: {out}: in use by another ringscan run (batch, process "
                           f"{holder.pid}); wait for it to end or choose another output folder (lock file "
                           f"{LOCK_NAME})")
        assert sorted(p.name for p in out.iterdir()) == [LOCK_NAME]  # nothing written
    finally:
        holder.kill()
        holder.wait()
    # the holder was killed: its lock file is left, its lock is gone; the next run takes it over
    assert (out / LOCK_NAME).read_text().split() == [str(holder.pid), "batch"]
    assert main(["batch", str(scan_root), "--out", str(out), "--workers", "0", "--no-progress", "--device", "cpu"]) == 0
    assert not (out / LOCK_NAME).exists()  # removed when the run ends


def test_an_unknown_device_is_the_commands_error_not_every_scans(scan_root, tmp_path, capsys):
    out = tmp_path / "out"
    # a device this machine does not have: the run fails on its input (exit 1), not on its usage
    assert main(["batch", str(scan_root), "--out", str(out), "--device", "bogus", "--no-progress"]) == 1
    assert "ringscan batch: error: device 'bogus': unknown (known: cpu" in capsys.readouterr().err
    assert not out.exists()  # before: every scan 'failed' as if its worker had crashed, exit 1


def test_a_device_number_with_the_ray_backend_is_refused_before_anything(scan_root, tmp_path, capsys):
    # a Ray task sees only the GPU Ray gave it, as cuda:0: cuda:1 would fail every scan on the nodes
    out = tmp_path / "out"
    assert main(["batch", str(scan_root), "--out", str(out), "--backend", "ray", "--device", "cuda:1",
                 "--no-progress"]) == 1
    err = capsys.readouterr().err
    assert "ringscan batch: error: device 'cuda:1' with the Ray backend" in err and "--device cuda" in err
    assert not out.exists()
