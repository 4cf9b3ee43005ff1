"""The ``ringscan`` command line.

Each sub-command lives in its own module ``ringscan.tools.cmd_<name>`` with two
functions: ``add_parser(subparsers)`` and ``run(args) -> int``. The device is chosen
here, once, at the edge (``--device``), and handed down.
"""

from __future__ import annotations

import argparse
import importlib
import logging
import sys

from ringscan.pipeline.formats.errors import RingscanError, show_path

log = logging.getLogger("ringscan")

# Sub-commands in the order `ringscan --help` lists them.
COMMANDS = [
    "demo",
    "patterns",
    "simulate",
    "reconstruct",
    "batch",
    "evaluate",
    "fuse",
    "mesh",
    "view",
    "sweep",
    "calibrate",
    "import",
    "pack",
    "unpack",
    "capture",
    "emulate",
    "bench",
]


def build_parser(command: str | None = None) -> argparse.ArgumentParser:
    """The parser of every sub-command, or of ``command`` alone (a known name): a
    process that runs one command then imports that command's module only (the others
    pull in SciPy, pygame, Open3D ...: seconds of start-up)."""
    p = argparse.ArgumentParser(
        prog="ringscan",
        description="Structured-light 3D scanning with concentric ring patterns.",
    )
    p.add_argument("-v", "--verbose", action="count", default=0, help="more log output (-vv for debug)")
    sub = p.add_subparsers(dest="command", metavar="COMMAND")
    for name in ([command] if command in COMMANDS else COMMANDS):
        mod = importlib.import_module(f"ringscan.tools.cmd_{name}")
        sp = mod.add_parser(sub)
        sp.set_defaults(_run=mod.run)
    return p


def add_device_option(p: argparse.ArgumentParser) -> None:
    """The one --device option every computing sub-command shares."""
    p.add_argument("--device", default=None,
                   help='Warp device: "cpu", "cuda", "cuda:N" (default: CUDA when present, else cpu)')


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    # The global options take no value: the first other word names the command.
    parser = build_parser(next((a for a in argv if not a.startswith("-")), None))
    args = parser.parse_args(argv)
    level = (logging.WARNING, logging.INFO, logging.DEBUG)[min(args.verbose, 2)]
    logging.basicConfig(level=level, format="%(levelname)s %(name)s: %(message)s")
    if not getattr(args, "_run", None):
        parser.print_help()
        return 2
    # This process is ringscan's: keep freed arrays' pages for the next view. Imported
    # here, not at the top, so that importing the capture command (real drivers) loads
    # no kernels and no Warp (tests/hardware/devices/test_camera.py).
    from ringscan.kernels.runtime import retain_freed_memory

    retain_freed_memory()
    try:
        return int(args._run(args) or 0)
    except RingscanError as e:
        print(f"ringscan {args.command}: error: {e}", file=sys.stderr)
        return 2
    except ValueError as e:
        print(f"ringscan {args.command}: error: {e}", file=sys.stderr)
        return 2
    except OSError as e:  # the disk, not the input: full, read-only, no permission
        where = f"{show_path(e.filename)}: " if e.filename else ""
        print(f"ringscan {args.command}: error: {where}{e.strerror or e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"ringscan {args.command}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
