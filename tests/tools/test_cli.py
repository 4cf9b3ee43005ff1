"""The conventions every command shares (docs/cli.md): version, verbosity anywhere,
help on every option, exit status, progress off a terminal, a fast --help."""

from __future__ import annotations

import argparse
import importlib
import logging
import subprocess
import sys
from importlib.metadata import version

import pytest

import ringscan
from ringscan.pipeline.formats.progress import progress_bar, progress_step
from ringscan.tools import cli
from ringscan.tools.cli import COMMANDS, build_parser, main

HEAVY = ("scipy", "open3d", "warp", "cv2")


def _walk(parser, path=()):
    """(command path, parser) of every parser below the top one."""
    for a in parser._actions:
        if isinstance(a, argparse._SubParsersAction):
            for name, sp in a.choices.items():
                yield (*path, name), sp
                yield from _walk(sp, (*path, name))


def test_version_is_the_installed_metadata(capsys):
    assert ringscan.__version__ == version("ringscan")
    with pytest.raises(SystemExit) as e:
        main(["--version"])
    assert e.value.code == 0
    assert capsys.readouterr().out.strip() == f"ringscan {version('ringscan')}"


def test_python_dash_m_ringscan():
    r = subprocess.run([sys.executable, "-m", "ringscan", "--version"], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0 and r.stdout.strip() == f"ringscan {version('ringscan')}", r.stderr


def test_help_loads_no_heavy_library():
    # Measured by what is imported, not by the clock: the listing imports no command module.
    code = ("import sys, contextlib, io\n"
            "from ringscan.tools.cli import main\n"
            "with contextlib.redirect_stdout(io.StringIO()) as out, contextlib.suppress(SystemExit):\n"
            "    main(['--help'])\n"
            f"print([m for m in {HEAVY!r} if m in sys.modules], 'reconstruct' in out.getvalue())")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    assert r.stdout.strip() == "[] True", r.stdout


def test_every_command_is_listed_and_builds():
    p = build_parser("*")
    built = {path[0] for path, _ in _walk(p)}
    assert built == set(COMMANDS)


def test_every_command_module_is_in_the_listing():
    # `ringscan --help` lists the commands from cli.COMMANDS without importing them: a new
    # tools/cmd_<name>.py needs its line there.
    import pkgutil

    import ringscan.tools

    modules = {m.name[4:] for m in pkgutil.iter_modules(ringscan.tools.__path__) if m.name.startswith("cmd_")}
    assert set(COMMANDS) <= modules
    # the rest are cmd_<command>_<group>.py: a group of <command>'s sub-commands, in its module's GROUPS
    for part in sorted(modules - set(COMMANDS)):
        owner = next((c for c in COMMANDS if part.startswith(c + "_")), None)
        assert owner is not None, f"tools/cmd_{part}.py is no command in cli.COMMANDS"
        groups = getattr(importlib.import_module(f"ringscan.tools.cmd_{owner}"), "GROUPS", ())
        assert f"ringscan.tools.cmd_{part}" in {g.__name__ for g in groups}, part


def test_every_option_has_help():
    missing = []
    for path, sp in _walk(build_parser("*")):
        for a in sp._actions:
            if not isinstance(a, argparse._SubParsersAction) and not a.help:
                missing.append(f"{' '.join(path)} {'/'.join(a.option_strings) or a.dest}")
    assert not missing, missing


def test_common_options_on_every_command():
    for path, sp in _walk(build_parser("*")):
        opts = sp._option_string_actions
        assert "-v" in opts and "-q" in opts, path
        leaf = not any(isinstance(a, argparse._SubParsersAction) for a in sp._actions)
        assert not leaf or "--no-progress" in opts, path


def test_truth_takes_a_mesh_or_a_scan_everywhere():
    seen = []
    for path, sp in _walk(build_parser("*")):
        a = sp._option_string_actions.get("--truth")
        if a is not None:
            seen.append(path)
            assert a.metavar == "MESH_OR_SCAN", (path, a.metavar)
    assert {p[0] for p in seen} >= {"view", "evaluate", "fuse"}


@pytest.mark.parametrize("where", ["before", "after"])
def test_verbose_and_quiet_before_or_after_the_command(tmp_path, capsys, where):
    for flag, level in (("-v", logging.INFO), ("-vv", logging.DEBUG), ("-q", logging.ERROR)):
        rest = ["reconstruct", str(tmp_path / "no_scan"), "--out", str(tmp_path / "o")]
        argv = [flag, *rest] if where == "before" else [*rest, flag]
        assert main(argv) == 1  # ran, and failed on its input (no scan there): not a usage error
        assert logging.getLogger("ringscan").level == level, (flag, where)
        err = capsys.readouterr().err
        assert err.startswith("ringscan reconstruct: error: ") and "no_scan" in err, err


def test_exit_status_usage_error_is_2(tmp_path, capsys):
    with pytest.raises(SystemExit) as e:
        main(["reconstruct", "--no-such-option"])
    assert e.value.code == 2
    # options that cannot be taken, found by the command before anything runs
    assert main(["demo", "--views", "0", "--out", str(tmp_path / "d")]) == 2
    err = capsys.readouterr().err
    assert "ringscan demo: error: --views must be at least 1" in err and "--help" in err
    assert not (tmp_path / "d").exists()


def test_schema_prints_the_settings_files_json_schema(capsys, tmp_path):
    import json

    assert main(["schema", "settings"]) == 0
    schema = json.loads(capsys.readouterr().out)
    assert schema["properties"]["min_confidence"]["type"] == "number"
    assert schema["properties"]["decode"]["$ref"] == "#/$defs/DecodeSettings"
    assert main(["schema", "capture-settings", "--out", str(tmp_path / "c.json")]) == 0
    cap = json.loads((tmp_path / "c.json").read_text())
    assert cap["properties"]["retries"]["type"] == "integer"
    assert cap["properties"]["retries"]["description"].startswith("Further attempts")


def test_no_command_is_a_usage_error(capsys):
    assert main([]) == 2
    assert "usage: ringscan" in capsys.readouterr().err


def test_exit_status_failed_run_is_1(tmp_path, capsys):
    bad = tmp_path / "cloud.ply"
    bad.write_text("not a ply")
    assert main(["mesh", str(bad), "--out", str(tmp_path / "m.ply")]) == 1
    err = capsys.readouterr().err.strip()
    assert err.startswith("ringscan mesh: error: ") and str(bad) in err and "Traceback" not in err


def test_exit_status_interrupted_is_130(tmp_path, capsys, monkeypatch):
    from ringscan.tools import cmd_view

    def interrupted(args):
        raise KeyboardInterrupt

    monkeypatch.setattr(cmd_view, "run", interrupted)
    assert main(["view", "x.ply", "--out", str(tmp_path / "x.png")]) == 130
    assert capsys.readouterr().err.strip() == ("ringscan view: interrupted; what was written so far is whole "
                                               "(a rerun starts over)")


def test_module_entry_point_shares_the_usage_error(tmp_path):
    # `python -m ringscan.tools.cli`: the commands' UsageError is still a usage error.
    r = subprocess.run([sys.executable, "-m", "ringscan.tools.cli", "demo", "--views", "0", "--out",
                        str(tmp_path / "d")], capture_output=True, text=True, timeout=300)
    assert r.returncode == 2, r.stderr


def test_progress_off_a_terminal_is_one_plain_line_per_step(caplog):
    assert not cli.sys.stderr.isatty()  # pytest captures stderr
    with caplog.at_level(logging.INFO, logger="ringscan.progress"):
        assert list(progress_bar(range(3), desc="reconstruct cup", unit="view")) == [0, 1, 2]
        with progress_step("Poisson meshing"):
            pass
    lines = [r.getMessage() for r in caplog.records if r.name == "ringscan.progress"]
    # the first and the last step (the loop is quicker than one line's interval), then the single step
    assert [ln.split(",")[0] for ln in lines[:2]] == [f"reconstruct cup: {i}/3 view(s)" for i in (1, 3)]
    assert lines[2] == "Poisson meshing ..." and lines[3].startswith("Poisson meshing: done in ")
    assert not any("\r" in ln for ln in lines)


def test_no_progress_is_silent(caplog):
    with caplog.at_level(logging.INFO, logger="ringscan.progress"):
        list(progress_bar(range(3), desc="x", unit="view", disable=True))
        with progress_step("y", enabled=False):
            pass
    assert not [r for r in caplog.records if r.name == "ringscan.progress"]


def test_warp_cuda_warning_hidden_unless_verbose():
    code = ("import logging, sys\n"
            "if sys.argv[1] == 'v': logging.basicConfig(level=logging.INFO)\n"
            "from ringscan.kernels.runtime import init_warp\n"
            "import warp as wp\n"
            "init_warp()\n"
            "print(wp.is_cuda_available())")
    quiet = subprocess.run([sys.executable, "-c", code, "q"], capture_output=True, text=True, timeout=300)
    assert quiet.returncode == 0, quiet.stderr
    assert "CUDA warning" not in quiet.stderr, quiet.stderr
    if quiet.stdout.strip() == "True":
        pytest.skip("this machine has CUDA: Warp prints no driver warning to hide")
    loud = subprocess.run([sys.executable, "-c", code, "v"], capture_output=True, text=True, timeout=300)
    assert "Could not find or load the NVIDIA CUDA driver" in loud.stderr, loud.stderr
