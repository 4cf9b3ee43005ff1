"""The Ray backend on a local cluster: the local backend's bytes, a worker killed mid-task survived, a GPU
asked for where the cluster has them, scans on object storage.

The tests that need no cluster in this process (an unreachable ``--address``; a ``batch`` process that starts
its own cluster and is killed) come first; the tests of :class:`TestOneCluster` then share one local cluster,
started once (a cluster's start is most of a Ray test's time) and shut down after the class."""

import pytest

from ringscan.pipeline.batch import batch_reconstruct
from ringscan.pipeline.batch.report import read_results
from ringscan.pipeline.batch.worker import FAULT_ENV

ray = pytest.importorskip("ray", reason="ray is not installed: pip install '.[ray]'")


@pytest.fixture(scope="module")
def local_out(three_scans, tmp_path_factory):
    """The three scans done by the local backend: the bytes every Ray run must give."""
    local = tmp_path_factory.mktemp("local") / "out"
    batch_reconstruct(three_scans, local, workers=0, device="cpu", progress=False)
    return local


def test_an_unreachable_address_fails_fast_and_writes_nothing(scan_root, tmp_path, capsys):
    import time

    from ringscan.tools.cli import main

    out = tmp_path / "out"
    t = time.perf_counter()
    rc = main(["batch", str(scan_root), "--out", str(out), "--backend", "ray", "--address", "127.0.0.1:1",
               "--no-progress"])
    err = capsys.readouterr().err.strip()
    assert rc == 1 and err == ("ringscan batch: error: --address 127.0.0.1:1: no Ray cluster answers there "
                               "(Connection refused)")
    assert time.perf_counter() - t < 30 and not out.exists()
    rc = main(["batch", str(scan_root), "--out", str(out), "--backend", "ray", "--address", "nohost", "--no-progress"])
    assert rc == 2 and "expected HOST:PORT or ray://HOST:PORT" in capsys.readouterr().err  # malformed: usage
    assert not out.exists() and not ray.is_initialized()


def _descendants(pid):
    """Every process below ``pid`` (children, theirs, ...)."""
    from pathlib import Path

    found, todo = [], [pid]
    while todo:
        p = todo.pop()
        for task in Path(f"/proc/{p}/task").glob("*"):
            try:
                kids = [int(c) for c in (task / "children").read_text().split()]
            except OSError:
                continue
            found += kids
            todo += kids
    return found


def _alive(pid):
    from pathlib import Path

    try:
        return "State:\tZ" not in Path(f"/proc/{pid}/status").read_text()
    except OSError:
        return False


def _holds_session_file(pid, session_re):
    import os

    try:
        fds = os.listdir(f"/proc/{pid}/fd")
    except OSError:
        return False
    for fd in fds:
        try:
            if session_re.search(os.readlink(f"/proc/{pid}/fd/{fd}")):
                return True
        except OSError:
            pass
    return False


@pytest.mark.slow
@pytest.mark.skipif(not __import__("sys").platform.startswith("linux"), reason="reads /proc (Linux)")
def test_a_killed_batch_leaves_no_ray_process_behind(three_scans, tmp_path):
    """`batch --backend ray` starts a local cluster; SIGKILL the batch while its tasks run: within 10 s no
    process of that Ray session is left (Ray alone leaves its two agents for a minute or more)."""
    import os
    import re
    import signal
    import subprocess
    import sys
    import time

    env = {k: v for k, v in os.environ.items() if k not in ("RAY_ADDRESS", "RINGSCAN_BATCH_FAULT")}
    proc = subprocess.Popen([sys.executable, "-m", "ringscan.tools.cli", "batch", str(three_scans), "--out",
                             str(tmp_path / "out"), "--backend", "ray", "--no-progress", "--device", "cpu"],
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, env=env)
    try:
        def names(pids):
            out = {}
            for p in pids:
                try:
                    out[p] = open(f"/proc/{p}/cmdline", "rb").read().split(b"\0")[0].decode(errors="replace")
                except OSError:
                    pass
            return out

        # kill once the raylet has started its agents and a worker (the tasks are starting: the batch is running)
        deadline = time.monotonic() + 120
        while proc.poll() is None and time.monotonic() < deadline:
            seen = names(_descendants(proc.pid))
            tags = set(seen.values())
            if {"ray::DashboardAgent", "ray::RuntimeEnvAgent"} <= tags and tags & {"ray::IDLE", "ray::_task"}:
                break
            time.sleep(0.02)
        assert proc.poll() is None, "the batch ended before it could be killed"
        assert time.monotonic() < deadline, f"no Ray worker started: {sorted(tags)}"
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait()
        session = re.compile(rf"/session_[^/]*_{proc.pid}(/|$)")  # the session Ray named after the batch
        deadline = time.monotonic() + 10
        while time.monotonic() < deadline:
            left = {p: n for p, n in seen.items() if _alive(p)}
            left |= {int(p): "?" for p in os.listdir("/proc")
                     if p.isdigit() and int(p) != os.getpid() and _holds_session_file(int(p), session)}
            if not left:
                break
            time.sleep(0.2)
        assert not left, f"still running 10 s after the batch was killed: {left}"
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()


@pytest.fixture(scope="class")
def cluster(tmp_path_factory):
    """One local cluster (a head node of 2 CPUs, no GPU) for the tests of a class, this process its driver; yields the
    kill-once marker path and the cluster (:class:`ray.cluster_utils.Cluster`: a test may add a node). Its
    switches are set before it starts, as Ray's workers take the driver's environment then: the marker (a
    worker dies only once a test creates the file) and the name of a scan whose worker raises (``c_raises``,
    only in the test that has it)."""
    from types import SimpleNamespace

    from ray.cluster_utils import Cluster

    from ringscan.pipeline.batch.worker import RAISE_ENV

    marker = tmp_path_factory.mktemp("fault") / "kill-once"
    env = pytest.MonkeyPatch()
    env.setenv(FAULT_ENV, str(marker))
    env.setenv(RAISE_ENV, "c_raises")
    # no GPU declared (Ray would count the machine's): the GPU test adds a node that has one
    nodes = Cluster(initialize_head=True, head_node_args={"num_cpus": 2, "num_gpus": 0, "include_dashboard": False})
    try:
        ray.init(address=nodes.address, log_to_driver=False, configure_logging=False)
        yield SimpleNamespace(marker=marker, nodes=nodes)
    finally:
        ray.shutdown()
        nodes.shutdown()
        env.undo()


@pytest.mark.slow
class TestOneCluster:
    """Batches on one running cluster, one after the other (each its own output folder); the last adds a node
    with a GPU."""

    def test_ray_tasks_read_packed_scans_to_the_same_bytes(self, cluster, three_scans, local_out, tmp_path):
        """Packed scans on Ray give the local backend's bytes; on a cluster without GPUs each task asks for one
        CPU and gets it (the report says what Ray gave it), and no worker dies while no test asks for it.
        (Unpacked scans on Ray: test_ray_survives_a_killed_worker_with_the_local_bytes, next.)"""
        import shutil

        from ringscan.pipeline.formats.packing import pack_scan

        packed = tmp_path / "packed"
        shutil.copytree(three_scans, packed)
        for scan in sorted(packed.glob("*/scan.json")):
            assert pack_scan(scan.parent).converted
        rep = batch_reconstruct(packed, tmp_path / "ray", backend="ray", device="cpu", progress=False)
        assert [s["status"] for s in rep["scans"]] == ["done"] * 3
        assert [s["ray_resources"] for s in rep["scans"]] == [{"CPU": 1.0}] * 3
        assert not cluster.marker.with_name("kill-once.taken").exists()  # no worker died for it

        def plys(folder):
            return {p.relative_to(folder): p.read_bytes() for p in sorted(folder.rglob("*.ply"))}

        assert plys(tmp_path / "ray") == plys(local_out) and len(plys(local_out)) == 4

    def test_ray_survives_a_killed_worker_with_the_local_bytes(self, cluster, three_scans, local_out, tmp_path):
        """A worker killed mid-task (SIGKILL after one view of its scan): Ray retries the task, the scan resumes,
        and the three (unpacked) scans give the local backend's bytes."""
        want = read_results(local_out)
        cluster.marker.write_text("")
        rep = batch_reconstruct(three_scans, tmp_path / "killed", backend="ray", device="cpu", progress=False)
        assert cluster.marker.with_name("kill-once.taken").exists()  # a worker did die
        # the killed scan's retry keeps the view its first attempt wrote (a one-view scan is then found done)
        assert {s["status"] for s in rep["scans"]} <= {"done", "skipped (already done)"}
        assert read_results(tmp_path / "killed") == want

    def test_ray_a_huge_frame_or_a_library_error_fails_its_scan_alone(self, cluster, scan_root, tmp_path):
        """On Ray as on the local pool: a frame of 60000x60000 px fails its scan alone, named, without a word of
        retries (none happened); so does a scan whose worker raises OpenCV's own exception; a task that cannot
        start its worker (a device that does not exist) names the error."""
        import shutil

        from ringscan.pipeline.batch.worker import RAISE_ENV
        from tests.support.header_only import huge_png

        root = tmp_path / "root"
        shutil.copytree(scan_root, root)
        shutil.copytree(scan_root / "a_sphere", root / "c_raises")  # the cluster's RAISE_ENV names it
        frame = root / "b" / "cube" / "view_000" / "gray_1.png"
        huge_png(frame)
        rep = batch_reconstruct(root, tmp_path / "ray", backend="ray", device="cpu", progress=False)
        bad = batch_reconstruct(scan_root, tmp_path / "bad", backend="ray", device="nodevice:7", progress=False)
        status = {s["scan"]: s for s in rep["scans"]}
        assert status["a_sphere"]["status"] == "done"
        assert status["b/cube"]["status"] == "failed"
        assert status["b/cube"]["error"].startswith(f"{frame}: image is 60000x60000 (3600 megapixels)")
        assert status["c_raises"] == {**status["c_raises"], "status": "failed",
                                      "error": f"cv2.error: {RAISE_ENV}: OpenCV's own exception, raised on purpose"}
        for s in bad["scans"]:
            assert s["status"] == "failed" and "nodevice:7" in s["error"] and "retries" not in s["error"], s

    def test_ray_tasks_read_and_write_s3(self, cluster, scan_root, local_out):
        """Ray tasks stage their scans from S3 (a local S3 server) as local workers do: the storage options
        (endpoint and credentials) travel with each task, no shared disk (the server's credentials are set in
        this process's environment only after the cluster started); the local backend's PLYs."""
        pytest.importorskip("s3fs", reason="the object-storage tests need s3fs (pip install '.[test]')")
        pytest.importorskip("moto.server", reason="the object-storage tests need moto (pip install '.[test]')")
        from tests.support.s3 import objects, plys, s3_server, upload

        with s3_server() as (options, fs):
            fs.mkdir("scans")
            upload(fs, scan_root, "s3://scans/root")
            fs.mkdir("ray")
            rep = batch_reconstruct("s3://scans/root", "s3://ray/run", backend="ray", device="cpu", progress=False,
                                    storage_options=options)
            assert [s["status"] for s in rep["scans"]] == ["done", "done"]
            got = {k: v for k, v in objects(fs, "s3://ray/run").items() if k.endswith(".ply")}
        want = {k: v for k, v in plys(local_out).items() if not k.startswith("c_turn/")}
        assert set(want) == {"a_sphere/view_000.ply", "b/cube/view_000.ply"} and got == want

    def test_ray_tasks_ask_for_a_gpu_where_the_cluster_has_them(self, cluster, scan_root, local_out, tmp_path):
        """A node that declares one GPU joins (Ray lets a node declare GPUs it does not check): every task then
        asks for a GPU and gets it (the batch report says what Ray gave each task), and the scan is done with
        the bytes of the local backend (the tasks are told to compute on the CPU, so the bytes match also on a
        node with a real GPU). Last in the class: the cluster keeps the node."""
        import shutil

        from ringscan.pipeline.batch.ray_backend import task_options

        assert task_options({"CPU": 8.0}) == {"num_cpus": 1}
        assert task_options({"CPU": 8.0, "GPU": 2.0}) == {"num_gpus": 1, "num_cpus": 1}
        cluster.nodes.add_node(num_cpus=1, num_gpus=1)
        cluster.nodes.wait_for_nodes()
        root = tmp_path / "root"  # one scan: a task given a GPU starts a worker process of its own (max_calls=1)
        shutil.copytree(scan_root / "a_sphere", root / "a_sphere")
        rep = batch_reconstruct(root, tmp_path / "ray", backend="ray", device="cpu", progress=False)
        assert [(s["status"], s["ray_resources"].get("GPU")) for s in rep["scans"]] == [("done", 1.0)]
        ply = "a_sphere/view_000.ply"
        assert (tmp_path / "ray" / ply).read_bytes() == (local_out / ply).read_bytes()
