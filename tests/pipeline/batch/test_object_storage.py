"""``ringscan batch`` and ``reconstruct`` through object storage: scans read from and results written to an
S3 server that the tests start (moto's, on a free port), against the same batch on local folders."""

import dataclasses
import json
import math
import shutil
import time

import pytest

pytest.importorskip("s3fs", reason="the object-storage tests need s3fs (pip install '.[test]')")
pytest.importorskip("moto.server", reason="the object-storage tests need moto (pip install '.[test]')")

from ringscan.pipeline.batch import batch_reconstruct, plan_batch  # noqa: E402
from ringscan.pipeline.batch.worker import FAULT_ENV, ScanJob, process_scan  # noqa: E402
from ringscan.pipeline.formats import storage  # noqa: E402
from ringscan.pipeline.formats.packing import pack_scan  # noqa: E402
from ringscan.pipeline.formats.storage import StorageError  # noqa: E402
from ringscan.tools.cli import main  # noqa: E402
from tests.support.s3 import objects, plys, s3_server, upload  # noqa: E402


@pytest.fixture(scope="module")
def s3():
    """A local S3 server for the module: (storage options pointing at it, an s3fs file system on it)."""
    with s3_server() as server:
        yield server


@pytest.fixture(scope="module")
def local_run(scan_root, tmp_path_factory):
    """The two scans done locally, in this process: the reference bytes."""
    out = tmp_path_factory.mktemp("local") / "out"
    rep = batch_reconstruct(scan_root, out, workers=0, device="cpu", progress=False)
    assert [s["status"] for s in rep["scans"]] == ["done", "done"]
    return out


@pytest.fixture(scope="module")
def scans_bucket(s3, scan_root):
    options, fs = s3
    fs.mkdir("scans")
    upload(fs, scan_root, "s3://scans/root")
    return "s3://scans/root"


def test_same_plys_through_s3_and_a_rerun_skips(s3, scans_bucket, local_run):
    options, fs = s3
    fs.mkdir("out")
    rep = batch_reconstruct(scans_bucket, "s3://out/run", workers=0, device="cpu", progress=False,
                            storage_options=options)
    assert [(s["scan"], s["status"]) for s in rep["scans"]] == [("a_sphere", "done"), ("b/cube", "done")]
    got = objects(fs, "s3://out/run")
    ref = plys(local_run)
    assert set(ref) == {"a_sphere/view_000.ply", "b/cube/view_000.ply"}
    assert {k: v for k, v in got.items() if k.endswith(".ply")} == ref  # byte-identical PLYs
    report = json.loads(got["a_sphere/report.json"])
    assert report["scan"] == "s3://scans/root/a_sphere"  # the URL, not the staging folder
    assert report["totals"]["points"] > 0
    per_view = rep["totals"]["per_view_s"]  # the time on object storage, beside the stages
    assert per_view["fetch"] > 0 and per_view["store"] > 0 and per_view["read"] > 0
    assert json.loads(got["batch_report.json"])["root"] == "s3://scans/root"
    assert not any(k.startswith(".") or "/." in k for k in got)  # no temporary object, no lock
    # a rerun decides from the listing and the results: nothing computed, no frame downloaded
    fetched = []
    real = storage.Staged.fetch_frames
    storage.Staged.fetch_frames = lambda self, *a, **k: (fetched.append(self.scan_location), real(self, *a, **k))
    try:
        again = batch_reconstruct(scans_bucket, "s3://out/run", workers=0, device="cpu", progress=False,
                                  storage_options=options)
        plans = plan_batch(scans_bucket, "s3://out/run", storage_options=options)
    finally:
        storage.Staged.fetch_frames = real
    assert [s["status"] for s in again["scans"]] == ["skipped (already done)"] * 2
    assert again["totals"]["computed_views"] == 0 and fetched == []
    assert [(p.scan, p.action, p.why) for p in plans] == [("a_sphere", "skip", "done"), ("b/cube", "skip", "done")]
    # a frame replaced on S3 (new modification time) makes that scan run again, the other stays done
    key = "scans/root/b/cube/view_000/black.png"
    # S3 times are whole seconds: the copy is written in a later second than the upload (waiting only for it)
    uploaded = fs.info(key)["LastModified"].timestamp()
    time.sleep(max(0.0, math.floor(uploaded) + 1.05 - time.time()))
    fs.pipe_file(key, fs.cat_file(key))
    plans = plan_batch(scans_bucket, "s3://out/run", storage_options=options)
    assert [(p.scan, p.action, p.why) for p in plans] == [("a_sphere", "skip", "done"),
                                                          ("b/cube", "run", "changed inputs")]


def test_packed_scan_through_s3_local_results(s3, scan_root, local_run, tmp_path):
    """A packed scan (Zarr chunks) read from S3, its results written to a local folder: the same PLY."""
    options, fs = s3
    scan = tmp_path / "a_sphere"
    shutil.copytree(scan_root / "a_sphere", scan)
    pack_scan(scan)
    assert any(p.name == "zarr.json" for p in scan.rglob("*"))
    fs.mkdir("packed")
    upload(fs, scan, "s3://packed/a_sphere")
    entry = process_scan(ScanJob(folder="s3://packed/a_sphere", rel="a_sphere", out=str(tmp_path / "out"),
                                 storage_options=options))
    assert entry["status"] == "done", entry
    assert (tmp_path / "out" / "view_000.ply").read_bytes() == (local_run / "a_sphere" / "view_000.ply").read_bytes()
    assert json.loads((tmp_path / "out" / "report.json").read_text())["scan"] == "s3://packed/a_sphere"


def test_fused_through_s3(s3, scans_bucket, scan_root, tmp_path):
    """--fuse through S3: fused/ stored with the local bytes; a rerun keeps it."""
    options, fs = s3
    fs.mkdir("fused")
    local = process_scan(ScanJob(folder=str(scan_root / "a_sphere"), rel="a", out=str(tmp_path / "a"), fuse=True))
    job = ScanJob(folder=f"{scans_bucket}/a_sphere", rel="a", out="s3://fused/a", fuse=True, storage_options=options)
    entry = process_scan(job)
    assert (local["fused"], entry["fused"], entry["fused_out"]) == ("done", "done", "s3://fused/a/fused")
    assert fs.cat_file("fused/a/fused/fused.ply") == (tmp_path / "a" / "fused" / "fused.ply").read_bytes()
    assert json.loads(fs.cat_file("fused/a/fused/fuse.json"))["source"] == "s3://fused/a"
    again = process_scan(job)
    assert (again["status"], again["fused"]) == ("skipped (already done)", "kept")


def test_bad_scans_on_s3_named_by_url(s3, scan_root, tmp_path, monkeypatch):
    """The loader's checks name the URL: a missing frame; a frame larger than ringscan reads (refused before
    it is downloaded); a missing bucket."""
    options, fs = s3
    fs.mkdir("bad")
    upload(fs, scan_root / "a_sphere", "s3://bad/a")
    frames = sorted(k for k in fs.find("bad/a/view_000") if k.endswith(".png"))
    fs.rm(frames[0])
    name = frames[0].rsplit("/", 1)[1][:-4]
    entry = process_scan(ScanJob(folder="s3://bad/a", rel="a", out="s3://bad/out", storage_options=options))
    assert entry["status"] == "failed"
    assert entry["error"] == (f"s3://{frames[0]}: frame {name!r} of view_000 not found (listed in scan.json "
                              "views[0].frames)")
    upload(fs, scan_root / "a_sphere", "s3://bad/a")
    monkeypatch.setattr(storage, "MAX_OBJECT_BYTES", 1000)
    entry = process_scan(ScanJob(folder="s3://bad/a", rel="a", out="s3://bad/out", storage_options=options))
    assert entry["status"] == "failed"
    assert entry["error"].startswith("s3://bad/a/view_000/") and "bytes: larger than the 1000 bytes a frame may " \
                                                                  "have" in entry["error"]
    assert fs.find("bad/out") == []  # nothing written for a scan that failed
    entry = process_scan(ScanJob(folder="s3://no-such-bucket/a", rel="a", out=str(tmp_path / "o"),
                                 storage_options=options))
    assert entry["error"] == "s3://no-such-bucket/a: bucket not found"


def test_killed_worker_on_s3(s3, scans_bucket, local_run, tmp_path, monkeypatch):
    """A worker SIGKILLed mid-scan (after one view, before its results are stored): the pool is replaced, the
    scan done again; the results are the local run's bytes and the killed worker's staging folder is removed."""
    options, fs = s3
    marker = tmp_path / "fault"
    marker.touch()
    monkeypatch.setenv(FAULT_ENV, str(marker))
    stage_dir = tmp_path / "stage"
    stage_dir.mkdir()
    monkeypatch.setenv("TMPDIR", str(stage_dir))  # the workers' staging folders
    fs.mkdir("killed")
    rep = batch_reconstruct(scans_bucket, "s3://killed/run", workers=1, device="cpu", cpu_threads=1, progress=False,
                            storage_options=options)
    assert not marker.exists()  # the fault was taken
    assert [s["status"] for s in rep["scans"]] == ["done", "done"]
    got = objects(fs, "s3://killed/run")
    assert {k: v for k, v in got.items() if k.endswith(".ply")} == plys(local_run)
    assert list(stage_dir.iterdir()) == []


def test_bucket_deleted_mid_batch(s3, scan_root, local_run, monkeypatch):
    """The scans' bucket deleted after the first scan is stored: the second fails with one line naming its URL,
    nothing of it is written; then the output bucket deleted: the batch stops with one line naming it."""
    options, fs = s3
    fs.mkdir("gone-in")
    upload(fs, scan_root, "s3://gone-in/root")
    fs.mkdir("gone-out")
    real = storage.Staged.commit
    commits = []

    def commit_then_delete(self):
        n = real(self)
        commits.append(self.out_location)
        if len(commits) == 1:
            fs.rm("gone-in", recursive=True)
        return n

    monkeypatch.setattr(storage.Staged, "commit", commit_then_delete)
    rep = batch_reconstruct("s3://gone-in/root", "s3://gone-out/run", workers=0, device="cpu", progress=False,
                            storage_options=options)
    assert [s["status"] for s in rep["scans"]] == ["done", "failed"]
    assert rep["scans"][1]["error"] == "s3://gone-in/root/b/cube: bucket not found"
    got = objects(fs, "s3://gone-out/run")
    assert sorted(got) == ["a_sphere/report.json", "a_sphere/settings.json", "a_sphere/view_000.ply",
                           "batch_report.json"]
    assert got["a_sphere/view_000.ply"] == (local_run / "a_sphere" / "view_000.ply").read_bytes()
    # now the output bucket goes away after the first scan
    fs.mkdir("gone-in")
    upload(fs, scan_root, "s3://gone-in/root")
    commits.clear()

    def commit_then_delete_out(self):
        n = real(self)
        commits.append(self.out_location)
        if len(commits) == 1:
            fs.rm("gone-out", recursive=True)
        return n

    monkeypatch.setattr(storage.Staged, "commit", commit_then_delete_out)
    with pytest.raises(StorageError) as e:
        batch_reconstruct("s3://gone-in/root", "s3://gone-out/run2", workers=0, device="cpu", progress=False,
                          storage_options=options)
    assert str(e.value) == "s3://gone-out/run2/batch_report.json: bucket not found"
    assert not fs.exists("gone-out")


def test_reconstruct_command_through_s3(s3, scans_bucket, local_run, capsys):
    options, fs = s3
    fs.mkdir("cli")
    opts = ["--storage-option", f"endpoint_url={options['endpoint_url']}", "--storage-option", "key=testing",
            "--storage-option", "secret=testing"]
    assert main(["reconstruct", f"{scans_bucket}/b/cube/scan.json", "--out", "s3://cli/cube", "--device", "cpu",
                 "--no-progress", *opts]) == 0
    assert fs.cat_file("cli/cube/view_000.ply") == (local_run / "b" / "cube" / "view_000.ply").read_bytes()
    assert "report: s3://cli/cube/report.json" in capsys.readouterr().out


def test_command_line_errors_are_one_line(s3, scan_root, tmp_path, capsys):
    """A missing bucket, an endpoint that does not answer (within seconds), a bad --storage-option: one line
    each, no traceback, exit status 1 (2 for the usage error), nothing written."""
    options, _ = s3
    endpoint = ["--storage-option", f"endpoint_url={options['endpoint_url']}"]
    for args, code, line in (
            (["s3://no-such-bucket/scans", *endpoint], 1,
             "ringscan batch: error: s3://no-such-bucket/scans: bucket not found"),
            (["s3://scans/root", "--storage-option", "endpoint_url=http://127.0.0.1:9", "--storage-option",
              "config_kwargs.retries.total_max_attempts=1"], 1,  # botocore: one try, no back-off
             "ringscan batch: error: s3://scans/root: cannot reach the storage service (Could not connect to the "
             "endpoint URL"),
            (["s3://scans/root", "--storage-option", "novalue"], 2,
             "ringscan batch: error: --storage-option 'novalue': expected KEY=VALUE"),
            # before: a raw `TypeError: AioSession.__init__() got an unexpected keyword argument` line, exit 1
            (["s3://scans/root", *endpoint, "--storage-option", "bogus=1"], 2,
             "ringscan batch: error: --storage-option bogus: not an option of the s3:// file system")):
        t = time.perf_counter()
        assert main(["batch", *args, "--out", str(tmp_path / "o"), "--device", "cpu"]) == code
        assert time.perf_counter() - t < 30
        err = capsys.readouterr().err.strip()
        assert len(err.splitlines()) == 1 and err.startswith(line), err
    # an output bucket that is not there: refused before anything runs
    assert main(["batch", str(scan_root), "--out", "s3://no-such-bucket/out", *endpoint]) == 1
    assert capsys.readouterr().err.strip().endswith("s3://no-such-bucket/out: cannot be the batch's output folder: "
                                                    "bucket 'no-such-bucket' not found")
    assert not (tmp_path / "o").exists()


def test_file_urls_are_local_folders(scan_root, local_run):
    plans = plan_batch(f"file://{scan_root}", f"file://{local_run}")
    assert [(p.scan, p.action, p.why) for p in plans] == [("a_sphere", "skip", "done"), ("b/cube", "skip", "done")]


def test_storage_options_parse():
    assert storage.parse_storage_options(["endpoint_url=http://h:9000", "anon=true", "config_kwargs.retries."
                                          "max_attempts=2", "key=abc"]) == {
        "endpoint_url": "http://h:9000", "anon": True, "config_kwargs": {"retries": {"max_attempts": 2}},
        "key": "abc"}
    assert storage.is_url("s3://b/p") and storage.is_url("gs://b") and not storage.is_url("file:///tmp/x")
    assert not storage.is_url("/tmp/x") and str(storage.local_path("file:///tmp/x")) == "/tmp/x"


def test_a_url_without_a_bucket_is_one_line(tmp_path, capsys):
    """`batch s3:// --out s3://out/x`: before, `TypeError: 'NoneType' object is not subscriptable`."""
    for argv in (["batch", "s3://", "--out", "s3://out/x"], ["reconstruct", "s3:///x", "--out", str(tmp_path / "o")]):
        assert main(argv) == 1
        err = capsys.readouterr().err.strip()
        assert err == (f"ringscan {argv[0]}: error: {argv[1]}: names no bucket: expected SCHEME://BUCKET/PATH (e.g. "
                       "s3://scans/2024)"), err
    assert not (tmp_path / "o").exists()


def test_storage_errors_in_one_line():
    """What the storage libraries raise, as one line naming the URL (refused credentials cannot be
    produced by moto's server without its IAM emulation: the mapping is checked here)."""
    url = "s3://b/scan"
    cases = [(FileNotFoundError("The specified bucket does not exist"), "s3://b/scan: bucket not found"),
             (FileNotFoundError("b/scan/scan.json"), "s3://b/scan: not found"),
             (PermissionError("The AWS Access Key Id you provided does not exist in our records."),
              "s3://b/scan: access denied: check the credentials and the bucket's permissions (The AWS Access Key "
              "Id you provided does not exist in our records.)"),
             (ConnectionRefusedError("[Errno 111] Connection\nrefused"),
              "s3://b/scan: cannot reach the storage service ([Errno 111] Connection refused)")]
    for exc, line in cases:
        assert str(storage.storage_error(url, exc)) == line
    try:
        from botocore.exceptions import NoCredentialsError
    except ImportError:
        return
    assert str(storage.storage_error(url, NoCredentialsError())).startswith("s3://b/scan: no credentials found: set "
                                                                            "AWS_ACCESS_KEY_ID")


def test_two_camera_scan_through_s3(s3, tmp_path):
    """A two-camera scan (camera 2's frames under <view>/cam2/) read from S3, as image files and packed
    (camera 2's store too): the same PLY as the local reconstruction, every rays setting's inputs staged."""
    from ringscan.pipeline.reconstruct.scan import reconstruct_scan
    from tests.support.batch_scans import SPEC
    from tests.support.tiny_scan import tiny_rig
    from tests.support.two_camera_scan import simulate_two_camera_scan, two_camera_rig

    options, fs = s3
    png = tmp_path / "png"
    # two_camera_rig's poses with the tiny scan's 160x128 cameras and 256x192 projector, the batch scans'
    # patterns and the angle patterns that stereo matching needs: about 300 stereo matches
    rig, tiny = two_camera_rig(), tiny_rig()
    small = {"width": tiny.camera.width, "height": tiny.camera.height, "K": tiny.camera.K}
    rig = dataclasses.replace(rig, light=tiny.light, camera=dataclasses.replace(rig.camera, **small),
                              camera2=dataclasses.replace(rig.camera2, **small))
    simulate_two_camera_scan(png, patterns={**SPEC, "angle_steps": 4, "angle_period": 12.0}, rig=rig)
    ref = reconstruct_scan(png, tmp_path / "local", progress=False)
    assert ref["views"][0]["rays"] == "all" and ref["views"][0]["stereo"]["matches"] > 0
    packed = tmp_path / "packed"
    shutil.copytree(png, packed)
    pack_scan(packed)
    assert (packed / "view_000" / "cam2" / "frames.zarr" / "zarr.json").is_file()
    fs.mkdir("stereo")
    for name, folder in (("png", png), ("packed", packed)):
        upload(fs, folder, f"s3://stereo/{name}")
        entry = process_scan(ScanJob(folder=f"s3://stereo/{name}", rel=name, out=str(tmp_path / "out" / name),
                                     storage_options=options))
        assert entry["status"] == "done", entry
        assert entry["calibration_check"]["kind"] == "epipolar"
        assert ((tmp_path / "out" / name / "view_000.ply").read_bytes()
                == (tmp_path / "local" / "view_000.ply").read_bytes()), name
