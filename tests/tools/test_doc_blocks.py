"""Every command block of README.md and docs/*.md is accounted for: run here as written (the
cheap ones), run by ``benchmarks/run_doc_blocks.py`` (the slow ones and the install), or named as
needing hardware or your photos, with the reason (the list and its reasons: that script's BLOCKS)."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from tests.support.benchmark_scripts import load_benchmark

ROOT = Path(__file__).resolve().parents[2]


DB = load_benchmark("run_doc_blocks")
CLASSIFIED = DB.classify()


def _block(match):
    (hit,) = [c for c in CLASSIFIED if c[0].match == match]
    return hit


def test_every_command_block_is_listed_with_where_it_runs():
    docs = {b.doc for b, *_ in CLASSIFIED}
    # pages without a command block
    assert set(DB.DOCS) - docs <= {"docs/bad_input.md", "docs/cli.md", "docs/design.md", "docs/formats.md",
                                   "docs/index.md", "docs/settings.md"}
    assert {"README.md", "docs/api.md", "docs/fusion.md", "docs/virtual_rig.md"} <= docs and len(CLASSIFIED) >= 50
    assert set(DB.DOCS) == {"README.md", *(f"docs/{p.name}" for p in (ROOT / "docs").glob("*.md"))}
    for b, line, lang, text in CLASSIFIED:
        assert b.where in ("suite", "script", "no") and b.reason, f"{b.doc}:{line}"
        if b.where == "suite":  # the test that runs it exists
            path, name = b.reason.split(" ")[0].split("::")
            assert re.search(rf"^def {name}\(", (ROOT / path).read_text(), re.M), b.reason
        for key in b.drop_lines:
            assert key in text, (b.doc, line, key)


def test_a_new_block_must_be_listed(tmp_path, monkeypatch):
    """A block added to a doc without an entry (or an entry whose block is gone) fails the list."""
    readme = (ROOT / "README.md").read_text()
    fake = tmp_path / "README.md"
    fake.write_text(readme + "\n```sh\nringscan view out/demo/mesh/mesh.ply\n```\n")
    (tmp_path / "docs").mkdir()
    for doc in DB.DOCS[1:]:
        (tmp_path / doc).write_text((ROOT / doc).read_text())
    monkeypatch.setattr(DB, "ROOT", tmp_path)
    with pytest.raises(ValueError, match=r"README.md:\d+: a sh block with 0 entries"):
        DB.classify()
    fake.write_text(readme + "\n```\nringscan view out/demo/mesh/mesh.ply\n```\n")  # a command without the tag
    with pytest.raises(ValueError, match="without the sh language tag"):
        DB.classify()
    fake.write_text(readme + "\n```sh\nmake demo    # again\n```\n")  # an entry whose text two blocks hold
    with pytest.raises(ValueError, match="matches more than one block"):
        DB.classify()
    start = readme.index("```sh\nmake demo")
    fake.write_text(readme[:start] + readme[readme.index("```", start + 5) + 3:])  # the block removed
    with pytest.raises(ValueError, match="no block contains 'make demo    #'"):
        DB.classify()


def test_a_usage_synopsis_is_not_a_command():
    """An untagged usage line (placeholders in capitals, [options], a|b) is not a command that escapes the
    list; an untagged line a reader could paste is."""
    for line in ("ringscan batch ROOT --out OUT [--workers N]", "ringscan pack SCAN_OR_ROOT --keep",
                 "ringscan capture --rig RIG --patterns P.json --views 8 --out SESSION \\",
                 "ringscan demo --out DIR --scene spot|sphere"):
        assert DB.is_synopsis(line), line
    for line in ("ringscan simulate --scene sphere --codec rings --out scan9     # the codec's defaults: 9 RINGS",
                 "ringscan reconstruct scans/sphere2 --out rec/sphere2 --rays camera-camera"):
        assert not DB.is_synopsis(line), line


def test_hardware_fault_injection_block_runs_as_written(tmp_path):
    """docs/hardware.md's fault injection on the emulated turntable and projector, as written: every
    fault it names is a kind the emulators take (a renamed kind or argument fails here)."""
    block, line, lang, text = _block('tt.inject("error", on="G1", code=33)')
    r = DB.run_block(block, lang, text, tmp_path / "work", timeout=120)
    assert r.returncode == 0, r.stdout + r.stderr


def test_readme_python_block_runs_as_written(tmp_path):
    """README's Python snippet, unchanged, on a scan in the demo's layout (out/demo/scan, view_000)."""
    block, line, lang, text = _block('report = reconstruct_scan("out/demo/scan"')
    r = DB.run_block(block, lang, text, tmp_path / "work", timeout=600)
    assert r.returncode == 0, r.stdout + r.stderr
    totals, count = r.stdout.strip().splitlines()[-2:]
    n = int(count.split()[0])
    assert count == f"{n} points in view_000" and n > 100 and f"'points': {n}" in totals
    assert (tmp_path / "work" / "out" / "python_recon" / "view_000.ply").is_file()


def test_calibration_precompensated_patterns_block_runs_as_written(tmp_path):
    """docs/calibration.md §5 (pre-compensated patterns): the patterns line as written; the capture line
    needs a rig (left out, named in the list)."""
    block, line, lang, text = _block("ringscan patterns --codec phase-rings --rig rig.json --out pat")
    assert "ringscan capture " not in DB.runnable_text(block, text)
    r = DB.run_block(block, lang, text, tmp_path / "work", timeout=600)
    assert r.returncode == 0, r.stdout + r.stderr
    import json

    spec = json.loads((tmp_path / "work" / "pat" / "patterns.json").read_text())
    assert spec["codec"] == "phase-rings" and (spec["width"], spec["height"]) == (1024, 768)  # the rig's projector
