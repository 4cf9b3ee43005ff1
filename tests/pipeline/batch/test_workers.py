"""``ringscan batch`` on worker processes: same bytes whatever the workers, a dead worker's scan given again,
--dry-run's reasons, per-scan fusion and meshing."""

import shutil

import pytest

from ringscan.pipeline.batch import batch_reconstruct, plan_batch
from ringscan.pipeline.batch.report import read_results
from ringscan.pipeline.batch.worker import CRASH_ENV, FAULT_ENV, STAGES
from ringscan.pipeline.formats.atomic import read_json
from ringscan.pipeline.formats.ply import read_ply
from ringscan.tools.cli import main


@pytest.fixture(scope="module")
def reference(three_scans, tmp_path_factory):
    """The three scans done in this process, one after another."""
    out = tmp_path_factory.mktemp("ref") / "out"
    rep = batch_reconstruct(three_scans, out, workers=0, device="cpu", progress=False)
    assert [s["status"] for s in rep["scans"]] == ["done"] * 3
    return out


def test_same_bytes_whatever_the_workers(three_scans, reference, tmp_path):
    ref = read_results(reference)
    # PLYs byte for byte; reports without their clock times
    assert {"a_sphere/view_000.ply", "b/cube/report.json", "c_turn/view_001.ply"} <= set(ref)
    out = tmp_path / "out"
    rep = batch_reconstruct(three_scans, out, workers=2, device="cpu", progress=False)
    assert [s["scan"] for s in rep["scans"]] == ["a_sphere", "b/cube", "c_turn"]  # in folder order, not finish order
    assert read_results(out) == ref
    tot = rep["totals"]
    assert tot["computed_views"] == 4 and tot["status"] == {"done": 3}
    # the per-view time split: every stage measured
    assert all(tot["per_view_s"][k] > 0 for k in STAGES)
    assert read_json(out / "batch_report.json")["totals"]["computed_views"] == 4
    # each worker's start-up, once (a worker that got no scan has nothing to say), from its spawn: the
    # interpreter and ringscan's imports alone take more than 0.2 s, and every worker started within the
    # batch (not before the first result: the slower worker may start after the other's first scan is back);
    # no scan's entry keeps it
    ws = tot["worker_start_s"]
    assert 1 <= ws["workers"] <= 2 and 0.2 < ws["median"] <= ws["max"] < tot["wall_s"]
    assert not any("worker_start_s" in s for s in rep["scans"])


def test_a_killed_worker_is_replaced_and_its_scan_done_once(three_scans, reference, tmp_path, monkeypatch):
    """One worker (a pool's start is most of this test's time; a dead worker breaks the pool whatever its size):
    it takes the marker on its first scan (a_sphere, one view), finishes that view, then dies with two scans in
    flight; the new pool finds a_sphere done and does the others."""
    marker = tmp_path / "kill-once"
    marker.write_text("")
    monkeypatch.setenv(FAULT_ENV, str(marker))
    out = tmp_path / "out"
    rep = batch_reconstruct(three_scans, out, workers=1, device="cpu", progress=False)
    assert not marker.exists() and (tmp_path / "kill-once.taken").exists()
    # the scans in flight were given again: the one whose view was written before the pool broke is found done
    assert [s["status"] for s in rep["scans"]] == ["skipped (already done)", "done", "done"]
    assert read_results(out) == read_results(reference)


def test_a_scan_that_always_kills_its_worker_fails_alone(three_scans, reference, tmp_path, monkeypatch):
    """b/cube kills its worker every time: it shares the pool with another scan when it
    first dies (one worker, two scans in flight: b/cube and c_turn), yet only it fails (it
    is found by running the suspects one at a time); the others give the reference bytes."""
    from ringscan.pipeline.batch.local import MAX_DEATHS

    monkeypatch.delenv(FAULT_ENV, raising=False)
    monkeypatch.setenv(CRASH_ENV, "b/cube")
    out = tmp_path / "out"
    rep = batch_reconstruct(three_scans, out, workers=1, device="cpu", progress=False)
    by = {s["scan"]: s for s in rep["scans"]}
    assert by["b/cube"]["status"] == "failed"
    assert f"died {MAX_DEATHS} times while it ran alone" in by["b/cube"]["error"]
    assert by["a_sphere"]["status"] in ("done", "skipped (already done)")
    assert by["c_turn"]["status"] in ("done", "skipped (already done)")
    ref = {k: v for k, v in read_results(reference).items() if not k.startswith("b/cube")}
    got = {k: v for k, v in read_results(out).items() if not k.startswith("b/cube")}
    assert got == ref


def test_dry_run_says_why(three_scans, reference, tmp_path, capsys):
    root = tmp_path / "scans"
    shutil.copytree(three_scans, root, copy_function=shutil.copy)  # frames get new times: changed inputs
    out = tmp_path / "out"
    shutil.copytree(reference, out)
    plans = {p.scan: p for p in plan_batch(root, out)}
    assert {p.why for p in plans.values()} == {"changed inputs"}
    batch_reconstruct(root, out, workers=0, device="cpu", progress=False)
    (out / "c_turn" / "view_001.ply").unlink()
    shutil.rmtree(out / "b")
    rep = read_json(out / "a_sphere" / "settings.json")
    rep["min_confidence"] = 0.5
    (tmp_path / "s.json").write_text(__import__("json").dumps(rep))
    plans = {p.scan: (p.action, p.why) for p in plan_batch(root, out)}
    assert plans == {"a_sphere": ("skip", "done"), "b/cube": ("run", "new"), "c_turn": ("run", "incomplete")}
    assert main(["batch", str(root), "--out", str(out), "--dry-run", "--settings", str(tmp_path / "s.json")]) == 0
    text = capsys.readouterr().out
    assert "a_sphere  run   changed settings" in text and "b/cube    run   new" in text
    assert "3 scan(s): 3 to run, 0 done" in text
    assert not (out / "b").exists()  # a dry run writes nothing


def test_fuse_and_mesh_in_the_same_run(three_scans, tmp_path):
    root = tmp_path / "scans"
    root.mkdir()
    shutil.copytree(three_scans / "c_turn", root / "c_turn")
    out = tmp_path / "out"
    assert main(["batch", str(root), "--out", str(out), "--mesh", "--workers", "0", "--no-progress",
                 "--device", "cpu"]) == 0
    mesh = out / "c_turn" / "mesh"
    rep = read_json(mesh / "fuse_report.json")
    assert rep["outputs"]["meshes"] == ["mesh.ply"]
    # more points than one view gives: c_turn's two views have about 550 points each (about 850 once fused)
    assert len(read_ply(mesh / "fused.ply")["x"]) > 600
    # a rerun keeps the mesh (the reconstruction did not change)
    before = (mesh / "mesh.ply").stat().st_mtime_ns
    rep = batch_reconstruct(root, out, workers=0, device="cpu", mesh=True, progress=False)
    assert rep["scans"][0]["fused"] == "kept" and (mesh / "mesh.ply").stat().st_mtime_ns == before
    # --fuse alone: the fused cloud, no mesh
    rep = batch_reconstruct(root, out, workers=0, device="cpu", fuse=True, progress=False)
    fused = out / "c_turn" / "fused"
    assert rep["scans"][0]["fused"] == "done" and read_json(fused / "fuse.json")["source"] == str(out / "c_turn")
    assert len(read_ply(fused / "fused.ply")["x"]) == len(read_ply(mesh / "fused.ply")["x"])
    # another run gives the same bytes (docs/batch.md: Open3D on one thread; before, the
    # mesh had a triangle more or less from run to run)
    out2 = tmp_path / "out2"
    batch_reconstruct(root, out2, workers=0, device="cpu", mesh=True, progress=False)
    for name in ("fused.ply", "mesh.ply"):
        assert (out2 / "c_turn" / "mesh" / name).read_bytes() == (mesh / name).read_bytes(), name


def test_bad_workers_and_backend(scan_root, tmp_path, capsys):
    assert main(["batch", str(scan_root), "--out", str(tmp_path / "o"), "--workers", "two"]) == 2
    assert "--workers 'two'" in capsys.readouterr().err
    assert main(["batch", str(scan_root), "--out", str(tmp_path / "o"), "--address", "x:1"]) == 2
    with pytest.raises(ValueError, match="backend"):
        batch_reconstruct(scan_root, tmp_path / "o", backend="spark")


def test_default_workers_one_per_gpu_else_one_per_core(monkeypatch):
    """Where Warp sees CUDA devices, one worker per device, each given its own; one
    worker for one device asked for; else one worker per core. (No GPU here: Warp's
    device count is faked.)"""
    import os

    import warp as wp

    from ringscan.pipeline.batch import default_workers

    monkeypatch.setattr(wp, "get_cuda_device_count", lambda: 3)
    assert default_workers(None) == (3, ["cuda:0", "cuda:1", "cuda:2"])
    assert default_workers("cpu") == (os.cpu_count(), ["cpu"])
    assert default_workers("cuda") == (3, ["cuda:0", "cuda:1", "cuda:2"])
    assert default_workers("cuda:1") == (1, ["cuda:1"])  # one device asked for: one worker on it
    monkeypatch.setattr(wp, "get_cuda_device_count", lambda: 0)
    assert default_workers(None) == (os.cpu_count(), [None])


def test_each_worker_takes_its_own_device(monkeypatch):
    """init_worker takes one device name from the shared queue (one CUDA device per worker)."""
    import queue

    from ringscan.pipeline.batch import worker

    q = queue.Queue()
    for d in ("cpu", "cpu"):
        q.put(d)
    monkeypatch.setattr(worker, "_device", None)
    # this process is no worker: its start-up must not reach the next in-process batch's report
    monkeypatch.setattr(worker, "_start_s", None)
    monkeypatch.setattr(worker, "_started", False)
    worker.init_worker(devices=q)
    assert worker.worker_device() == "cpu" and q.qsize() == 1


def test_workers_exit_when_the_batch_process_is_killed(three_scans, tmp_path):
    import os
    import signal
    import subprocess
    import sys
    import time
    from pathlib import Path

    proc = subprocess.Popen([sys.executable, "-m", "ringscan.tools.cli", "batch", str(three_scans), "--out",
                             str(tmp_path / "out"), "--workers", "1", "--no-progress", "--device", "cpu"],
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)

    def children():
        try:
            return [int(c) for c in Path(f"/proc/{proc.pid}/task/{proc.pid}/children").read_text().split()]
        except OSError:
            return []

    deadline = time.monotonic() + 60
    while len(kids := children()) < 2 and proc.poll() is None and time.monotonic() < deadline:
        time.sleep(0.02)  # the worker and the resource tracker
    assert proc.poll() is None, "the batch ended before it could be killed"
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait()

    def running(pid):
        try:
            return "State:\tZ" not in Path(f"/proc/{pid}/status").read_text()
        except OSError:
            return False

    deadline = time.monotonic() + 10
    while any(running(k) for k in kids) and time.monotonic() < deadline:
        time.sleep(0.1)
    assert not any(running(k) for k in kids)


def test_a_worker_that_dies_between_scans_breaks_nothing(monkeypatch):
    """The pool can break while no scan is running on the dead worker (killed between two
    scans): the next submit then fails. The batch starts a new pool and every scan is
    still done exactly once. (A fake pool: the breakage at that moment cannot be timed
    with real processes.)"""
    from concurrent.futures import Future
    from concurrent.futures.process import BrokenProcessPool

    from ringscan.pipeline.batch import local
    from ringscan.pipeline.batch.worker import ScanJob

    pools = []

    class FakePool:
        def __init__(self, *a, **k):
            self.submitted = 0
            pools.append(self)

        def submit(self, fn, job):
            # the first pool breaks at its third submit, as if a worker had just died
            if len(pools) == 1 and self.submitted == 2:
                raise BrokenProcessPool("a worker died")
            self.submitted += 1
            f = Future()
            f.set_result({"scan": job.rel, "status": "done"})
            return f

        def shutdown(self, *a, **k):
            pass

    monkeypatch.setattr(local, "ProcessPoolExecutor", FakePool)
    jobs = [ScanJob(folder=f"/x/s{i}", rel=f"s{i}", out=f"/o/s{i}") for i in range(6)]
    got = list(local.run_local(iter(jobs), workers=2, devices=[None, None]))
    assert sorted(n for n, _ in got) == list(range(6))  # each scan once
    assert all(e["status"] == "done" for _, e in got)
    assert len(pools) == 2


def test_ctrl_c_ends_the_batch_and_its_workers_in_one_line(three_scans, tmp_path):
    """Ctrl-C at a terminal reaches every process of the group. Before: a KeyboardInterrupt traceback from every
    worker (~60 lines). Sent while the workers start (importing Warp: where an initializer comes too late)."""
    import os
    import signal
    import subprocess
    import sys
    import time

    from tests.support.processes import as_foreground_job, children, running

    proc = subprocess.Popen([sys.executable, "-m", "ringscan.tools.cli", "batch", str(three_scans), "--out",
                             str(tmp_path / "out"), "--workers", "2", "--no-progress", "--device", "cpu"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True,
                            preexec_fn=as_foreground_job)
    deadline = time.monotonic() + 60
    while len(kids := children(proc.pid)) < 3 and proc.poll() is None and time.monotonic() < deadline:
        time.sleep(0.02)  # two workers and the resource tracker
    assert proc.poll() is None, "the batch ended before Ctrl-C"
    os.killpg(proc.pid, signal.SIGINT)  # what the terminal does
    out, err = proc.communicate(timeout=30)
    assert proc.returncode == 130 and err.startswith("ringscan batch: interrupted") and err.count("\n") == 1, (
        proc.returncode, err)
    assert "finished scans are skipped" in err  # a rerun resumes, and the line says so
    deadline = time.monotonic() + 10
    while any(running(k) for k in kids) and time.monotonic() < deadline:
        time.sleep(0.1)
    assert not any(running(k) for k in kids)
