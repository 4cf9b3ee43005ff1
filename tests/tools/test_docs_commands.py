"""Every ``ringscan ...`` command line in README.md and docs/*.md parses with the
options the commands have now: a renamed or removed option makes the doc fail here."""

from __future__ import annotations

import contextlib
import io
import re
import shlex
from pathlib import Path

import pytest

from ringscan.tools.cli import COMMANDS, _command_of, build_parser

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
