"""What the ``ringscan calibrate`` sub-commands share: sizes and outputs checked, the board, fit and --force
options, the settings they make, and how views and calibrations are printed (tools/cmd_calibrate*.py)."""

from __future__ import annotations

import contextlib
import os
from pathlib import Path

from ringscan.pipeline.calibrate.board import ARUCO_DICTIONARIES, Board, BoardSettings, charuco_dictionary
from ringscan.pipeline.calibrate.camera import CameraSettings
from ringscan.pipeline.calibrate.errors import CalibrationError
from ringscan.pipeline.formats.atomic import check_no_overwrite, check_output_file
from ringscan.pipeline.formats.errors import FormatError
from ringscan.tools.cli import UsageError

MAX_SIZE = 65536
"""Largest width or height ``parse_size`` accepts (the rig file's limit)."""


def parse_size(text: str, what: str) -> tuple[int, int]:
    """'9x7' -> (9, 7); a clear error otherwise (each side 1..65536)."""
    if not isinstance(text, str):  # argparse gives `--board=--` as an empty list
        text = " ".join(map(str, text)) if isinstance(text, (list, tuple)) else str(text)
        text = text or "--"
    shown = text if len(text) <= 40 else text[:37] + "..."
    try:
        a, b = text.lower().split("x")
        if not (a.strip().isdigit() and b.strip().isdigit()) or len(a.strip()) > 6 or len(b.strip()) > 6:
            raise ValueError
        w, h = int(a), int(b)
    except ValueError:
        raise UsageError(f"{what}: expected WxH (e.g. 9x7), got {shown!r}") from None
    if not (0 < w <= MAX_SIZE and 0 < h <= MAX_SIZE):
        raise UsageError(f"{what}: sizes must be from 1 to {MAX_SIZE}, got {shown!r}")
    return w, h


def check_outputs(outputs: dict, inputs) -> None:
    """Refuse output files (option -> path; None: not given) that are the same file, that would overwrite an input,
    or that cannot be written as files, before anything is computed.

    Raises:
        FormatError: naming the output.
    """
    given = {opt: p for opt, p in outputs.items() if p}
    seen: dict = {}
    for opt, p in given.items():
        check_output_file(p, what=f"file {opt} writes")
        key = os.path.realpath(p)
        if key in seen:
            raise FormatError(p, f"given to both {seen[key]} and {opt}: one would overwrite the other")
        seen[key] = opt
    check_no_overwrite(list(given.values()), [str(i) for i in inputs])


def folder_files(folders) -> list[Path]:
    """The regular files directly in each folder (a capture's frames): outputs must not overwrite them."""
    out = []
    for f in folders:
        with contextlib.suppress(OSError):
            out += [Path(e.path) for e in os.scandir(f) if e.is_file()]
    return out


def _charuco_arg(text: str) -> str:
    import argparse

    try:
        return charuco_dictionary(text)
    except ValueError as e:
        raise argparse.ArgumentTypeError(str(e)) from None


def add_board_options(p) -> None:
    g = p.add_argument_group("board")
    g.add_argument("--board", default="9x7", metavar="COLSxROWS", help="inner corners of the chessboard (default 9x7)")
    g.add_argument("--square", type=float, required=True, help="square size in mm (the rig's units)")
    g.add_argument("--charuco", type=_charuco_arg, default=None, metavar="DICT",
                   help="a ChArUco board with this predefined ArUco dictionary, any case (--board counts its inner "
                        "corners; OpenCV's layout before 4.6.0 is recognised by itself): "
                        + ", ".join(ARUCO_DICTIONARIES))
    g.add_argument("--marker", type=float, default=0.0, help="ChArUco marker size in mm (default 0.75 x square)")
    g.add_argument("--max-tilt", type=float, default=BoardSettings.max_tilt_deg,
                   help=f"reject views tilted more than this (degrees, default {BoardSettings.max_tilt_deg:g})")
    g.add_argument("--max-edge-width", type=float, default=BoardSettings.max_edge_width_px,
                   help=f"reject chessboards with edges wider than this (px, default {BoardSettings.max_edge_width_px:g})")


def add_fit_options(p) -> None:
    g = p.add_argument_group("fit")
    g.add_argument("--fix-k3", choices=("auto", "yes", "no"), default="auto",
                   help=f"hold k3 at 0 (auto: below {CameraSettings.k3_min_views} views)")
    g.add_argument("--fix-tangential", choices=("auto", "yes", "no"), default="auto",
                   help=f"hold p1, p2 at 0 (auto: below {CameraSettings.tangential_min_views} views)")
    g.add_argument("--min-views", type=int, default=CameraSettings.min_views,
                   help=f"fewest usable views (default {CameraSettings.min_views})")


def add_force_option(p) -> None:
    p.add_argument("--force", action="store_true",
                   help="write the result even where the calibration finds it cannot stand behind it (what it "
                        "cannot determine is printed as warnings); without it such a result is refused and "
                        "nothing is written")


def refuse_unless_forced(args, problems: list[str], out) -> None:
    """One line naming every problem and nothing written, unless --force (then warnings)."""
    if not problems:
        return
    if getattr(args, "force", False):
        for p in problems:
            print(f"warning: {p}")
        print("--force: writing it all the same")
        return
    raise CalibrationError(None, f"not writing {out}: {'; '.join(problems)} (--force writes it anyway)")


def print_duplicates(dups: list[str]) -> None:
    for d in dups:
        print(f"  {d}: the same board pose as the earlier view, left out")


def board_from_args(args) -> Board:
    cols, rows = parse_size(args.board, "--board")
    try:
        return Board(cols=cols, rows=rows, square=args.square, charuco=args.charuco, marker=args.marker)
    except ValueError as e:
        raise ValueError(f"--board/--square/--marker: {e}") from None


def board_settings_from_args(args) -> BoardSettings:
    if not 0 < args.max_edge_width <= 1000:
        raise ValueError(f"--max-edge-width: expected px from 0 to 1000, got {args.max_edge_width:g}")
    if not 0 < args.max_tilt <= 90:
        raise ValueError(f"--max-tilt: expected degrees from 0 to 90, got {args.max_tilt:g}")
    return BoardSettings(max_edge_width_px=args.max_edge_width, max_tilt_deg=args.max_tilt)


def camera_settings_from_args(args) -> CameraSettings:
    tri = {"auto": None, "yes": True, "no": False}
    model = getattr(args, "lens_model", "standard")  # procam has no --lens-model
    if model != "standard" and args.fix_k3 != "auto":
        raise UsageError(f"--fix-k3 applies to --lens-model standard only (the {model} model always fits k3)")
    return CameraSettings(min_views=args.min_views, fix_k3=tri[args.fix_k3], fix_tangential=tri[args.fix_tangential],
                          lens_model=model)


def print_views(views) -> None:
    for v in views:
        found = "found" + (" (ChArUco board of OpenCV's legacy layout, before 4.6.0)" if v.legacy else "")
        print(f"  {v.name}: {found if v.found else v.reason}")


def print_calibration(what: str, cal) -> None:
    print(f"{what}: RMS reprojection error {cal.rms:.3f} px over {len(cal.names)} views; "
          f"fx {cal.K[0, 0]:.1f} fy {cal.K[1, 1]:.1f} cx {cal.K[0, 2]:.1f} cy {cal.K[1, 2]:.1f}; "
          f"dist {', '.join(f'{x:.4g}' for x in cal.dist)}; fixed: {', '.join(cal.fixed) or 'none'}")
    for n, e in zip(cal.names, cal.per_view):
        flag = "  <- spoils the fit" if n in cal.outliers else ""
        print(f"  {n}: {e:.3f} px{flag}")
