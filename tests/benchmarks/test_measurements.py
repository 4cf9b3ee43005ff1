"""benchmarks/measurements.py and the page it writes, docs/measurements.md: the committed page is the
script's, with one section per entry in the list's order; ``--only`` reruns a section and keeps the others."""

import datetime as dt
from pathlib import Path

from tests.support.benchmark_scripts import load_benchmark

ROOT = Path(__file__).resolve().parents[2]


def _load(name: str):
    return load_benchmark(name)


M = _load("measurements")


def test_the_pages_check_block_runs_as_written():
    """docs/measurements.md's own block (``python benchmarks/measurements.py --check``), run as written from
    the repository root: the committed page passes."""
    db = _load("run_doc_blocks")
    (hit,) = [c for c in db.classify() if c[0].doc == "docs/measurements.md"]
    block, _, lang, text = hit
    assert "python benchmarks/measurements.py --check" in text
    r = db.run_block(block, lang, text, ROOT, timeout=60)
    assert r.returncode == 0, r.stdout + r.stderr
    assert f"{len(M.ENTRIES)} sections, as listed" in r.stdout


def test_the_entries_name_commands_that_exist():
    slugs = [e.slug for e in M.ENTRIES]
    assert len(set(slugs)) == len(slugs)
    for e in M.ENTRIES:
        script = e.command.split()[1]
        assert e.command.startswith("python benchmarks/") and (ROOT / script).is_file(), e.command
        assert e.timeout_s > 0 and e.about.endswith("."), e.title


def test_only_reruns_its_section_and_keeps_the_others(tmp_path, monkeypatch):
    page = tmp_path / "measurements.md"
    one = M.Entry("One", 'python -c "print(1)"', 30, "Prints 1.")
    two = M.Entry("Two, again", 'python -c "print(\'fresh output\')"', 30, "Prints a word.")
    gone = M.Entry("Gone", "python -c 1", 30, "No longer listed.")
    monkeypatch.setattr(M, "PAGE", page)
    monkeypatch.setattr(M, "ENTRIES", (one, two, gone))
    when = dt.datetime(2020, 1, 2, 3, 4, 5, tzinfo=dt.timezone.utc)
    old = {e.slug: M.section(e, when=when, where="an old machine", wall_s=1.0, status="exit status 0",
                             output=f"old output of {e.title}") for e in (one, two, gone)}
    page.write_text(M.render(old))
    assert M.check() == []

    monkeypatch.setattr(M, "ENTRIES", (one, two))
    assert M.check() == ["section 'gone' is for no entry of the list"]
    assert M.main(["--only", "two-again"]) == 0
    new = M.parse(page.read_text())
    assert list(new) == ["one", "two-again"]  # the list's order; the unlisted section dropped
    assert new["one"] == old["one"]  # kept byte for byte
    # the rerun's own printed line replaced the old one (a word: this is about sections, not figures)
    assert "old output" not in new["two-again"] and "\nfresh output\n" in new["two-again"]
    assert "2020-01-02" not in new["two-again"] and "exit status 0" in new["two-again"]
    assert M.check() == []

    monkeypatch.setattr(M, "ENTRIES", (two, one))
    assert M.check() and "order" in M.check()[0]
    page.write_text(page.read_text().replace(M.MARK, "hand-written"))
    monkeypatch.setattr(M, "ENTRIES", (one, two))
    assert "not generated" in M.check()[0]
    page.unlink()
    assert "no such page" in M.check()[0]


def test_clean_leaves_figures_and_drops_colours_and_start_up_lines():
    raw = ("Warp CUDA warning: Could not find or load the NVIDIA CUDA driver. GPU execution will not be available.\n"
           "Warp 1.19.0 initialized:\n   CUDA Toolkit 13.4, CUDA driver not available (NVRTC compilation available)\n"
           '   Devices:\n     "cpu"      : "CPU"\n   Kernel cache:\n     /root/.cache/warp/1.19.0\n'
           "Module ringscan.kernels.phase 1a2b3c4 load on device 'cpu' took 12.34 ms  (cached)\n"
           "[Open3D INFO] Window created\n\x1b[32mmedian 0.0123 mm\x1b[0m\nprogress 10 %\rprogress 100 %\n")
    assert M.clean(raw) == "median 0.0123 mm\nprogress 100 %"
