"""Every ``ringscan ...`` command line in README.md and docs/*.md parses with the
options the commands have now: a renamed or removed option makes the doc fail here."""

from __future__ import annotations

import contextlib
import io
import re
import shlex
from pathlib import Path

import pytest

from ringscan.tools.cli import COMMANDS, _command_of, build_parser, main
from tests.support.printed import assert_figures_as_quoted, printed_figure

ROOT = Path(__file__).resolve().parents[2]
DOCS = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
PLACEHOLDER = re.compile(r"invalid (int|float) value: '[A-Z_]+'")  # `--views N`: a placeholder, not an error


def _command_lines(text: str):
    """The `ringscan` command lines of a Markdown file's code blocks (continuations joined;
    usage lines with [optional], a|b or ... left out)."""
    code, lines = False, []
    for line in text.splitlines():
        if line.strip().startswith("```"):
            code = not code
        elif code:
            lines.append(line)
    for line in re.sub(r"\\\n\s*", " ", "\n".join(lines)).splitlines():
        line = line.strip().removeprefix("$ ")
        for part in re.split(r"\s*(?:&&|;|\|\|)\s*", line):
            if part.startswith(("ringscan ", ".venv/bin/ringscan ")):
                argv = shlex.split(part.split(" #")[0])[1:]
                if not any(c in a for a in argv for c in ("[", "|", "...")):
                    yield part, argv


CASES = [(p.name, part, argv) for p in DOCS for part, argv in _command_lines(p.read_text())]


def test_the_docs_name_commands():
    docs = {c[0] for c in CASES}
    assert len(CASES) > 40 and {"fusion.md", "calibration.md"} <= docs, docs


@pytest.mark.parametrize("doc, line, argv", CASES, ids=[f"{c[0]}:{c[1][:60]}" for c in CASES])
def test_doc_command_parses(doc, line, argv):
    cmd = _command_of(argv)
    assert cmd in COMMANDS, f"{doc}: {line}: no command {cmd!r}"
    err = io.StringIO()
    try:
        with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
            build_parser(cmd).parse_args(argv)
    except SystemExit as e:
        msg = err.getvalue().strip().splitlines()[-1] if err.getvalue().strip() else ""
        if e.code and not PLACEHOLDER.search(msg):
            pytest.fail(f"{doc}: {line}: {msg}")


def test_calibration_md_grey_ramp_runs_as_written(tmp_path, monkeypatch, capsys):
    """docs/calibration.md §5: the virtual rig's ramp, then the section's command on its rig file, as written."""
    import glob

    text = (ROOT / "docs" / "calibration.md").read_text()
    section = text[text.index("## 5. "):text.index("## 6. ")]
    snippet = re.search(r"```python\n(.*?)```", section, re.S).group(1)
    command = next(argv for _, argv in _command_lines(section)  # the one on the virtual rig's file
                   if argv[:2] == ["calibrate", "response"] and "ramp_rig.json" in argv)
    monkeypatch.chdir(tmp_path)
    exec(compile(snippet, "calibration.md §5", "exec"), {})
    argv = [a for arg in command for a in (sorted(glob.glob(arg)) if "*" in arg else [arg])]  # the shell's glob
    assert main(argv) == 0
    out = capsys.readouterr().out
    assert abs(printed_figure(out, "light gamma {}") - 2.2) < 0.05, out  # the light's gamma, found
    # the figure the doc quotes is the one it gives (to 1e-3 of it: the virtual rig's float32 render and the
    # fit may move the last digits on another CPU)
    assert_figures_as_quoted(out, section, "light gamma {} (camera gamma", rtol=1e-3,
                             why="the virtual rig's float32 render and the fit on another CPU")


def test_the_docs_index_lists_every_page_and_only_pages_that_exist():
    index = (ROOT / "docs" / "index.md").read_text()
    linked = set(re.findall(r"\]\(([\w.]+\.md)\)", index))
    pages = {p.name for p in (ROOT / "docs").glob("*.md")} - {"index.md"}
    assert linked == pages, (sorted(pages - linked), sorted(linked - pages))
    assert "(docs/index.md)" in (ROOT / "README.md").read_text()
