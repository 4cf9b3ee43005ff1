"""``ringscan batch``: every scan below a folder, failures listed, reruns resume."""

import pytest

from ringscan.pipeline.batch import batch_reconstruct, find_scans
from ringscan.pipeline.evaluate.metrics import evaluate_recon
from ringscan.pipeline.formats.atomic import read_json
from ringscan.pipeline.formats.errors import RingscanError
from ringscan.tools.cli import main


def test_batch_reconstructs_every_scan_and_resumes(scan_root, tmp_path):
    assert [p.relative_to(scan_root).as_posix() for p in find_scans(scan_root)] == ["a_sphere", "b/cube"]
    out = tmp_path / "out"
    rep = batch_reconstruct(scan_root, out, progress=False)
    assert [s["status"] for s in rep["scans"]] == ["done", "done"]
    for rel in ("a_sphere", "b/cube"):
        ev = evaluate_recon(out / rel, scan_root / rel)
        assert ev["all"]["median_mm"] < 0.1 and ev["all"]["frac_over_1mm"] < 0.01
    assert read_json(out / "batch_report.json")["scans"] == rep["scans"]
    ply = out / "a_sphere" / "view_000.ply"
    before = ply.stat().st_mtime_ns
    rep2 = batch_reconstruct(scan_root, out, progress=False)
    assert [s["status"] for s in rep2["scans"]] == ["skipped (already done)"] * 2
    assert ply.stat().st_mtime_ns == before  # nothing redone


def test_batch_lists_a_broken_scan_and_goes_on(scan_root, tmp_path):
    import shutil

    root = tmp_path / "root"
    shutil.copytree(scan_root, root)
    frame = root / "a_sphere" / "view_000" / "white.png"
    frame.write_bytes(b"not a png")
    out = tmp_path / "out"
    rep = batch_reconstruct(root, out, progress=False)
    status = {s["scan"]: s for s in rep["scans"]}
    assert status["a_sphere"]["status"] == "failed"
    assert "white.png" in status["a_sphere"]["error"] and "not a readable image" in status["a_sphere"]["error"]
    assert status["b/cube"]["status"] == "done"
    # the CLI says so and exits 1; the scan that worked is kept
    assert main(["batch", str(root), "--out", str(out), "--no-progress", "--device", "cpu"]) == 1
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
