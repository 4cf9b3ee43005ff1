"""Basic and advanced options (issue 36, "settings in two tiers"): `ringscan COMMAND --help` shows a command's
basic options and ends with how many more `--help-all` lists; an advanced option parses as before."""

from __future__ import annotations

import argparse
import re

import pytest

from ringscan.tools.cli import ESSENTIAL, _apply_tiers, basic_options, build_parser, main

SHARED = {"-h", "--help-all", "-v", "-q"}
"""On every parser alike, not counted in a command's bound."""

MAX_BASIC = 12
"""The most options one command's --help shows (positional arguments, --out, --device and --no-progress
included): capture (a real rig's devices, the virtual rig, resume) and batch (the cluster) need that many."""


def _leaves(p, path=()):
    subs = [a for a in p._actions if isinstance(a, argparse._SubParsersAction)]
    if not subs:
        yield path, p
    for s in subs:
        for name, sp in s.choices.items():
            yield from _leaves(sp, (*path, name))


def _help(argv, capsys) -> str:
    with pytest.raises(SystemExit) as e:
        main(argv)
    assert e.value.code == 0
    return capsys.readouterr().out


def _options(text: str) -> set:
    return set(re.findall(r"^\s{2}(-[-\w]+)", text, re.M))


def test_help_hides_an_advanced_option_and_says_how_many_more(capsys):
    text = _help(["reconstruct", "--help"], capsys)
    assert "--storage-option" not in text and "--views" not in _options(text)
    assert {"--out", "--settings", "--constraint", "--resume", "--device", "--no-progress"} <= _options(text)
    assert text.rstrip().splitlines()[-1] == ("2 more options (advanced): `ringscan reconstruct --help-all` "
                                             "lists every option.")
    text = _help(["calibrate", "camera", "--help"], capsys)
    assert "--fix-k3" not in _options(text) and "--square" in _options(text)  # a required option is always shown
    assert text.rstrip().splitlines()[-1].startswith("7 more options (advanced): `ringscan calibrate camera")


def test_help_all_shows_every_option(capsys):
    text = _help(["reconstruct", "--help-all"], capsys)
    assert {"--storage-option", "--views", "--out"} <= _options(text) and "more option" not in text
    text = _help(["capture", "--help-all"], capsys)
    assert {"--baud", "--retry-delay", "--flavor", "--virtual"} <= _options(text)
    assert "--settings" not in _options(text)  # an old spelling stays hidden


def test_the_listing_names_help_all(capsys):
    assert "`ringscan COMMAND --help-all` every option" in " ".join(_help(["--help"], capsys).split())
    assert "--help-all" in _help(["--help-all"], capsys)


def test_an_advanced_option_parses_as_before():
    args = build_parser("reconstruct").parse_args(["reconstruct", "s", "--out", "o", "--storage-option", "anon=true",
                                                   "--views", "a,b"])
    assert args.storage_options == ["anon=true"] and args.views == "a,b"
    args = build_parser("capture").parse_args(["capture", "--out", "o", "--baud", "9600", "--retries", "5"])
    assert args.baud == 9600 and args.retries == 5
    assert build_parser("capture").parse_args(["capture", "--out", "o"]).baud == 115200  # defaults unchanged
    with pytest.raises(SystemExit) as e:  # a bad value: the same usage error
        build_parser("capture").parse_args(["capture", "--out", "o", "--baud", "fast"])
    assert e.value.code == 2


@pytest.mark.parametrize("path, parser", list(_leaves(build_parser("*"))), ids=lambda x: " ".join(x)
                         if isinstance(x, tuple) else "")
def test_every_command_shows_a_few_options_and_lists_all(path, parser, capsys):
    shown = [a for a in parser._actions if a.help != argparse.SUPPRESS and not set(a.option_strings) & SHARED]
    advanced = [a for a in parser._actions if getattr(a, "_advanced_help", None) is not None]
    assert len(shown) <= MAX_BASIC, (path, [a.option_strings or a.dest for a in shown])
    for a in parser._actions:  # the essentials, positional arguments and required options: always basic
        if not a.option_strings or a.required or set(a.option_strings) & ESSENTIAL:
            assert a.help != argparse.SUPPRESS, (path, a.option_strings)
    text = _help([*path, "--help"], capsys)
    if advanced:
        assert text.rstrip().splitlines()[-1].startswith(f"{len(advanced)} more option")
    else:
        assert "--help-all` lists" not in text
    full = _options(_help([*path, "--help-all"], capsys))
    assert {a.option_strings[0] for a in advanced} <= full and _options(text) <= full


def test_basic_options_must_name_options():
    """A misspelt name in a command's basic_options fails when the parser is built, not silently."""
    p = argparse.ArgumentParser(prog="ringscan x")
    p.add_argument("--a")
    p.add_argument("--b")
    basic_options(p, "--a")
    _apply_tiers(p)
    assert p._option_string_actions["--a"].help is None and p._option_string_actions["--b"].help == argparse.SUPPRESS
    basic_options(p, "--c")
    with pytest.raises(ValueError, match="ringscan x: basic_options names no option --c"):
        _apply_tiers(p)
