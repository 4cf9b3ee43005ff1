"""The ``ringscan`` command line.

Each sub-command lives in its own module ``ringscan.tools.cmd_<name>`` with two
functions: ``add_parser(subparsers)`` and ``run(args) -> int``. Only the module of
the command given is imported (``ringscan --help`` loads no Warp, Open3D or SciPy).
The device is chosen here, once, at the edge (``--device``), and handed down.

The conventions every command follows (docs/cli.md) are set here: ``-v``/``-q``
before or after the command, ``--no-progress`` everywhere, progress bars only on a
terminal, and the exit status: 0 success, 1 a run that failed on its input or data,
2 a usage error, 130 interrupted. Help comes in two tiers: ``--help`` shows the basic
options a command declares with ``basic_options`` (and the essentials), ``--help-all``
every option; an advanced option parses as any other.
"""

from __future__ import annotations

import argparse
import importlib
import logging
import os
import sys

from ringscan.pipeline.formats.errors import RingscanError, show_path

log = logging.getLogger("ringscan")

EXIT_OK, EXIT_FAILED, EXIT_USAGE, EXIT_INTERRUPTED = 0, 1, 2, 130

# Sub-commands in the order `ringscan --help` lists them, with that listing's line
# (the command's module is imported only when it is the one given).
COMMANDS = {
    "demo": "simulate, reconstruct, evaluate, fuse, mesh and preview a default scan",
    "patterns": "write the projector frames of a pattern codec as PNG",
    "simulate": "render a scan of a virtual object (with ground truth)",
    "reconstruct": "reconstruct a scan folder into per-view point clouds",
    "batch": "reconstruct every scan below a folder, in parallel (resumable)",
    "evaluate": "point-to-surface error and coverage against ground truth",
    "fuse": "fuse turntable views into one cloud and mesh it",
    "mesh": "mesh a point cloud (Poisson or TSDF) into PLY, OBJ or STL",
    "view": "render point clouds and meshes to a PNG (offscreen)",
    "sweep": "error and coverage against the number of rings (the minimum ring count)",
    "calibrate": "calibrate a real rig: camera, projector (procam), response, light, turntable",
    "import": "real Gray-code captures -> a scan folder (decoded projector positions)",
    "pack": "pack a scan's frames into one compressed frame store per view (lossless, checked)",
    "unpack": "unpack a scan's frame stores back into image files",
    "capture": "capture a scan from a turntable rig (or the emulated virtual rig)",
    "emulate": "run an emulated rig (turntable, projector, camera) to try captures",
    "bench": "time decode, sampling and triangulation against NumPy",
    "schema": "print the JSON Schema of a settings file",
}


class UsageError(ValueError):
    """Options that do not fit together or a value an option cannot take: exit status 2."""


def check_frame_bits_option(bits: int | None) -> None:
    """``--frame-bits``: None, or a value ``check_frame_bits`` accepts.

    Raises:
        UsageError: naming the option and what it takes.
    """
    from ringscan.pipeline.formats.scan import check_frame_bits

    if bits is not None:
        try:
            check_frame_bits(bits, where="--frame-bits")
        except RingscanError as e:
            raise UsageError(str(e)) from None


class _VersionAction(argparse.Action):
    """``--version``: argparse's, the version read when asked for (the installed metadata: ~15 ms of every
    command's start otherwise)."""

    def __init__(self, option_strings, dest=argparse.SUPPRESS, default=argparse.SUPPRESS, help=None):
        super().__init__(option_strings=option_strings, dest=dest, default=default, nargs=0, help=help)

    def __call__(self, parser, namespace, values, option_string=None):
        parser._print_message(f"ringscan {_version()}\n", sys.stdout)
        parser.exit()


def _version() -> str:
    from ringscan import __version__

    return __version__


ESSENTIAL = frozenset({"-h", "--help", "--help-all", "-v", "--verbose", "-q", "--quiet", "--no-progress",
                       "--device", "--out"})
"""Options every ``--help`` shows where the command has them (docs/cli.md, "Basic and advanced options"), with
the positional arguments and the required options."""


def basic_options(p: argparse.ArgumentParser, *options: str) -> argparse.ArgumentParser:
    """Declare a command's basic options (any of each one's spellings): ``ringscan COMMAND --help`` shows them,
    the positional arguments, the required options and ``ESSENTIAL``; every other option is advanced, shown by
    ``--help-all`` only (it parses as before). A parser that declares none shows every option."""
    p._basic_options = frozenset(options)
    return p


class _Parser(argparse.ArgumentParser):
    """argparse's parser, whose help ends with how many advanced options ``--help-all`` adds."""

    def format_help(self) -> str:
        text = super().format_help()
        hidden = [a for a in self._actions if getattr(a, "_advanced_help", None) is not None
                  and a.help == argparse.SUPPRESS]
        if hidden:
            n = len(hidden)
            text += (f"\n{n} more option{'s' if n > 1 else ''} (advanced): "
                     f"`{self.prog} --help-all` lists every option.\n")
        return text


class _HelpAllAction(argparse.Action):
    """``--help-all``: the help with the advanced options too, then exit."""

    def __init__(self, option_strings, dest=argparse.SUPPRESS, default=argparse.SUPPRESS, help=None):
        super().__init__(option_strings=option_strings, dest=dest, default=default, nargs=0, help=help)

    def __call__(self, parser, namespace, values, option_string=None):
        for a in parser._actions:
            if getattr(a, "_advanced_help", None) is not None:
                a.help = a._advanced_help
        parser.print_help()
        parser.exit()


def _apply_tiers(p: argparse.ArgumentParser) -> None:
    """Hide the help of the options ``basic_options`` did not declare (their help kept for ``--help-all``)."""
    basic = getattr(p, "_basic_options", None)
    if basic is None:
        return
    known = {s for a in p._actions for s in a.option_strings}
    unknown = sorted(basic - known)
    if unknown:
        raise ValueError(f"{p.prog}: basic_options names no option {', '.join(unknown)}")
    for a in p._actions:
        if (not a.option_strings or a.required or a.help == argparse.SUPPRESS
                or {*a.option_strings} & (basic | ESSENTIAL)):
            continue
        a._advanced_help, a.help = a.help, argparse.SUPPRESS


def _add_common(p: argparse.ArgumentParser, level: int, *, leaf: bool) -> None:
    """-v/-q on every parser (each level counts into its own attribute, summed in
    main: argparse's sub-parsers would otherwise overwrite the level above);
    --help-all (listed right after -h) on every parser; --no-progress on every
    command that runs something."""
    a = p.add_argument("--help-all", action=_HelpAllAction,
                       help="show this help with every option, the advanced ones too, and exit")
    for actions in (p._actions, p._optionals._group_actions):
        actions.remove(a)
        actions.insert(1, a)
    p.add_argument("-v", "--verbose", action="count", default=0, dest=f"_verbose_{level}",
                   help="more log output (-vv: debug); allowed before or after the command")
    p.add_argument("-q", "--quiet", action="count", default=0, dest=f"_quiet_{level}",
                   help="only errors (no progress, no warnings); allowed before or after the command")
    if leaf and "--no-progress" not in p._option_string_actions:
        p.add_argument("--no-progress", action="store_true",
                       help="no progress bars or progress lines (bars are drawn only on a terminal)")


def _add_common_below(sub: argparse._SubParsersAction, level: int) -> None:
    for sp in set(sub.choices.values()):
        nested = [a for a in sp._actions if isinstance(a, argparse._SubParsersAction)]
        _add_common(sp, level, leaf=not nested)
        for n in nested:
            _add_common_below(n, level + 1)
        _apply_tiers(sp)


HELP_EPILOG = ("Every command: -v more log (-vv debug), -q errors only, --no-progress; exit status 0 done, 1 failed "
               "on its input (one line naming the file), 2 usage error, 130 interrupted (what was written is whole). "
               "`ringscan COMMAND --help` gives a command's basic options, `ringscan COMMAND --help-all` every option "
               "(the advanced ones too). Documentation: README.md, which an installed "
               "ringscan carries as its description (`python -c \"import importlib.metadata as m; "
               "print(m.metadata('ringscan').get_payload())\"` prints it), and docs/ in ringscan's source tree "
               "(docs/cli.md: these conventions in full).")
"""The listing's epilog: the conventions themselves (a wheel has no docs/ folder), and where the rest is."""

RESUME_HINT = {
    "reconstruct": "the same command with --resume keeps the views already done",
    "batch": "the same command again resumes: finished scans are skipped",
    "pack": "the same command again resumes", "unpack": "the same command again resumes",
    "capture": "`ringscan capture --out SCAN --resume` continues the capture",
}
"""What a rerun after Ctrl-C does, for the commands that resume (the others start over)."""


def interrupted_line(name: str) -> str:
    """The line Ctrl-C leaves: interrupted, what was written is whole, and whether a rerun resumes."""
    hint = RESUME_HINT.get(name.split(" ")[0], "a rerun starts over")
    return f"ringscan{' ' + name if name else ''}: interrupted; what was written so far is whole ({hint})"


def build_parser(command: str | None = None) -> argparse.ArgumentParser:
    """The parser; ``command`` (or every command when "*") gets its full options,
    the others only their line in the listing."""
    p = _Parser(
        prog="ringscan",
        description="Structured-light 3D scanning with concentric ring patterns.",
        epilog=HELP_EPILOG,
    )
    p.add_argument("--version", action=_VersionAction, help="print the version and exit")
    _add_common(p, 0, leaf=False)
    sub = p.add_subparsers(dest="command", metavar="COMMAND")
    for name, line in COMMANDS.items():
        if command not in (name, "*"):
            sub.add_parser(name, help=line, add_help=False)
            continue
        mod = importlib.import_module(f"ringscan.tools.cmd_{name}")
        sp = mod.add_parser(sub)
        sp.set_defaults(_run=mod.run)
    _add_common_below(sub, 1)
    return p


def add_device_option(p: argparse.ArgumentParser) -> None:
    """The one --device option every computing sub-command shares."""
    p.add_argument("--device", default=None,
                   help='Warp device: "cpu", "cuda", "cuda:N" (default: CUDA when present, else cpu)')


def _command_of(argv: list[str]) -> str | None:
    """The command named in argv: the first word that is not an option (the
    top-level options take no value)."""
    for a in argv:
        if a == "--":
            return None
        if not a.startswith("-"):
            return a
    return None


def _setup_logging(args: argparse.Namespace) -> None:
    verbose = sum(v for k, v in vars(args).items() if k.startswith("_verbose_"))
    quiet = sum(v for k, v in vars(args).items() if k.startswith("_quiet_"))
    level = logging.ERROR if quiet else (logging.WARNING, logging.INFO, logging.DEBUG)[min(verbose, 2)]
    logging.basicConfig(level=level, format="%(levelname)s %(name)s: %(message)s")  # a no-op where set up
    logging.getLogger("ringscan").setLevel(level)
    # Progress lines (off a terminal) are shown unless -q or --no-progress.
    show = not quiet and not getattr(args, "no_progress", False)
    logging.getLogger("ringscan.progress").setLevel(logging.INFO if show else logging.ERROR)
    args.verbose, args.quiet = verbose, quiet
    if quiet and hasattr(args, "no_progress"):
        args.no_progress = True


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    command = _command_of(argv)
    try:  # Ctrl-C while the command's modules load (Warp, Open3D: seconds): one line too
        parser = build_parser(command if command in COMMANDS else None)
    except KeyboardInterrupt:
        print(interrupted_line(command if command in COMMANDS else ""), file=sys.stderr)
        return EXIT_INTERRUPTED
    args = parser.parse_args(argv)
    _setup_logging(args)
    if not getattr(args, "_run", None):
        parser.print_help(sys.stderr)
        return EXIT_USAGE
    # This process is ringscan's: keep freed arrays' pages for the next view. Imported
    # here, not at the top, so that importing the capture command (real drivers) loads
    # no kernels and no Warp (tests/hardware/devices/test_camera.py).
    from ringscan.kernels.process import (freeze_imported_objects, one_blas_thread, retain_freed_memory,
                                          skip_final_collection)

    retain_freed_memory()
    one_blas_thread()  # BLAS threads spinning beside the kernels took the cores from them (docs/batch.md)
    skip_final_collection()  # the command's process ends without a last collection (~0.4 s)
    freeze_imported_objects()  # (the command's modules are imported: build_parser)
    name = " ".join([args.command, *([args.what] if getattr(args, "what", None) else [])])
    try:
        return int(args._run(args) or 0)
    except UsageError as e:
        print(f"ringscan {name}: error: {e} (see `ringscan {name} --help`)", file=sys.stderr)
        return EXIT_USAGE
    except ValueError as e:
        # A library check of an option's value names the option first (`--projector 'display:': ...`):
        # a usage error too. Everything else is the input or the data.
        print(f"ringscan {name}: error: {e}", file=sys.stderr)
        return EXIT_USAGE if not isinstance(e, RingscanError) and str(e).startswith("--") else EXIT_FAILED
    except RingscanError as e:
        print(f"ringscan {name}: error: {e}", file=sys.stderr)
        return EXIT_FAILED
    except BrokenPipeError:  # the reader went away (`ringscan schema settings | head`): stop quietly
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return EXIT_FAILED
    except OSError as e:  # the disk, not the input: full, read-only, no permission
        where = f"{show_path(e.filename)}: " if e.filename else ""
        print(f"ringscan {name}: error: {where}{e.strerror or e}", file=sys.stderr)
        return EXIT_FAILED
    except KeyboardInterrupt:
        print(interrupted_line(name), file=sys.stderr)
        return EXIT_INTERRUPTED


if __name__ == "__main__":
    # Through the module's installed name, so that the UsageError the commands raise is this one.
    from ringscan.tools.cli import main as _main

    sys.exit(_main())
