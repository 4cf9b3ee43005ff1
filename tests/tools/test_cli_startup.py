"""A ``ringscan`` process imports the module of the command it runs, not every command's."""

import subprocess
import sys
from pathlib import Path

from ringscan.tools.cli import COMMANDS, build_parser, main

REPO = Path(__file__).resolve().parents[2]

_PROBE = """
import sys
from ringscan.tools.cli import main
try:
    main(sys.argv[1:])
except SystemExit:
    pass
print("MODULES", " ".join(sorted(m for m in sys.modules if m.startswith("ringscan.tools.cmd_"))))
"""


def _modules(*argv):
    r = subprocess.run([sys.executable, "-c", _PROBE, *argv], capture_output=True, text=True, timeout=300, cwd=REPO)
    return r.stdout.split("MODULES", 1)[1].split()


def test_one_command_imports_its_module_only():
    assert _modules("-v", "pack", "--help") == ["ringscan.tools.cmd_pack"]
    # the listing comes from the command table: no command's module is imported for it
    assert _modules("--help") == [] and _modules("nonsense") == []


def test_full_parser_lists_every_command(capsys):
    p = build_parser()
    sub = next(a for a in p._actions if a.dest == "command")
    assert set(sub.choices) == set(COMMANDS)
    assert main(["-v"]) == 2  # no command: a usage error, with the command listing
    assert "usage: ringscan" in capsys.readouterr().err


def test_the_version_is_read_only_when_asked_for():
    """The installed metadata (importlib.metadata, ~15 ms) is read for ``--version``, not by every command's start
    (``import``'s: it loads no Warp, which reads it for itself)."""
    probe = ("import sys\nfrom ringscan.tools.cli import main\ntry:\n    main(sys.argv[1:])\nexcept SystemExit:\n"
             "    pass\nprint('METADATA', 'importlib.metadata' in sys.modules)\n")
    runs = {a: subprocess.run([sys.executable, "-c", probe, a, *(["--help"] if a == "import" else [])],
                              capture_output=True, text=True, timeout=300, cwd=REPO) for a in ("import", "--version")}
    assert runs["import"].stdout.split("METADATA")[1].split() == ["False"]
    assert runs["--version"].stdout.startswith("ringscan ") and runs["--version"].stdout.split("METADATA")[1].split() == ["True"]
