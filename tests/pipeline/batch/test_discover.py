"""Finding the scans of a batch: link loops and scans nested in scans are reported, never silently dropped."""

import os

from ringscan.pipeline.batch import find_scans


def _scan(folder):
    folder.mkdir(parents=True)
    (folder / "scan.json").write_text("{}")
    return folder


def test_a_link_loop_hides_no_scan_and_is_reported(tmp_path):
    root = tmp_path / "root"
    _scan(root / "a" / "s1")
    _scan(root / "a" / "s2")
    os.symlink("loop", root / "a" / "loop")  # loop -> loop
    os.symlink("nowhere", root / "a" / "broken")
    skipped = []
    found = [p.relative_to(root).as_posix() for p in find_scans(root, skipped=skipped)]
    assert found == ["a/s1", "a/s2"]
    why = dict(skipped)
    assert why[str(root / "a" / "loop")] == "cannot follow this link: too many levels of symbolic links"
    assert "a broken symbolic link" == why[str(root / "a" / "broken")]


def test_a_scan_inside_a_scan_is_reported(tmp_path):
    root = tmp_path / "root"
    outer = _scan(root / "outer")
    _scan(outer / "view_000" / "inner")
    (outer / "view_000" / "white.png").write_bytes(b"")
    skipped = []
    assert find_scans(root, skipped=skipped) == [outer]
    assert skipped == [(str(outer / "view_000" / "inner"),
                        f"a scan folder inside the scan folder {outer}: not processed (a scan folder's subfolders are "
                        "not searched; give it as a ROOT of its own)")]
    # the same when the scan folder is the root itself
    skipped = []
    assert find_scans(outer, skipped=skipped) == [outer] and len(skipped) == 1
