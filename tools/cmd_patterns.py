"""``ringscan patterns --codec ... --out DIR``: the projector frames of a codec as PNG files.

Writes ``<frame>.png`` for every frame, in projection order, plus ``patterns.json``
(the scan.json ``patterns`` block) and ``frames.txt`` (the frame names, one a line,
in projection order) for a real projector. The pattern options are shared with
``ringscan simulate``. ``--show [DISPLAY]`` puts the frames full-screen on a display
(a projector plugged in as a screen) and steps through them by hand, for aiming.

``--rig RIG`` writes the frames pre-compensated for the rig's light response
(``light.response.gamma``, from ``ringscan calibrate response``) and takes the
projector size from the rig; ``--precompensate GAMMA`` gives the gamma by hand.
The gamma goes into patterns.json (``precompensated_gamma``), so a capture of
these frames carries it and the phase decoder undoes only what is left.
"""

from __future__ import annotations

import argparse

from ringscan.hardware.devices.display import VIEWER_KEYS, DisplayProjector, run_viewer
from ringscan.pipeline.codecs import DEFAULT_CODEC
from ringscan.pipeline.codecs.render import render_frame
from ringscan.pipeline.formats.atomic import atomic_write_bytes, atomic_write_json, check_output_folder
from ringscan.pipeline.formats.images import write_image
from ringscan.pipeline.formats.patterns import CODECS, PatternSpec, default_patterns, frame_names, pattern_options
from ringscan.pipeline.formats.rig import load_rig
from ringscan.tools.cli import UsageError, basic_options


def add_pattern_options(p, *, size: bool = True) -> None:
    """The pattern options of ``patterns`` and ``simulate`` (``size``: also --width/--height/--center).
    An option not given takes its codec's default (``patterns.CODEC_DEFAULTS``); the codec
    options are ``patterns.pattern_options``, the default codec ``codecs.DEFAULT_CODEC``."""
    g = p.add_argument_group("pattern")
    g.add_argument("--codec", choices=CODECS, default=DEFAULT_CODEC, help=f"pattern codec (default {DEFAULT_CODEC})")
    for o in pattern_options():
        g.add_argument(o.flag, dest=o.dest, type=o.type, default=None, metavar=o.metavar, help=o.help)
    g.add_argument("--precompensate", type=float, default=None, metavar="GAMMA",
                   help="write grey levels pre-compensated for a light of this response gamma "
                        "(value = 255 v^(1/GAMMA), so the light emits v; default none)")
    if size:
        g.add_argument("--width", type=int, default=None,
                       help="projector width in px (default the rig's projector with --rig, else 1024)")
        g.add_argument("--height", type=int, default=None,
                       help="projector height in px (default the rig's projector with --rig, else 768)")
        g.add_argument("--ring-centre", dest="center", type=float, nargs=2, default=None, metavar=("CU", "CV"),
                       help="the rings' centre in projector px (default the image centre, (W-1)/2, (H-1)/2)")
        # The old spelling, hidden: --centre is the display's centring flag (patterns --show, capture).
        g.add_argument("--center", dest="center", type=float, nargs=2, help=argparse.SUPPRESS)


def pattern_spec_from_args(args, width: int, height: int, center=None, *,
                           precompensated_gamma: float | None = None) -> PatternSpec:
    """A validated :class:`PatternSpec` from the options of :func:`add_pattern_options`
    (``precompensated_gamma``, where given, stands for ``--precompensate``)."""
    pre = args.precompensate if precompensated_gamma is None else precompensated_gamma
    return default_patterns(args.codec, width=int(width), height=int(height),
                            center=None if center is None else [float(c) for c in center],
                            precompensated_gamma=pre, source="command line",
                            **{o.dest: getattr(args, o.dest, None) for o in pattern_options()})


def add_parser(sub):
    p = sub.add_parser("patterns", help="write the projector frames of a pattern codec as PNG",
                       description="Write every frame of a codec as <frame>.png (projection order in "
                                   "frames.txt) plus patterns.json, the scan.json 'patterns' block.")
    p.add_argument("--out", default=None, help="output folder")
    p.add_argument("--show", nargs="?", const="0", default=None, metavar="DISPLAY",
                   help="show the frames full-screen on this display (index or name; default 0) and step through "
                        "them with the arrow keys (b black, q quits), to aim the projector and the camera")
    p.add_argument("--centre", action="store_true", help="with --show: frames smaller than the display are centred")
    p.add_argument("--rig", default=None, metavar="RIG.json",
                   help="pre-compensate the frames for this rig's light response (light.response.gamma, "
                        "'ringscan calibrate response') and take the projector size from it")
    add_pattern_options(p)
    basic_options(p, "--show", "--rig", "--codec", "--bits", "--sector-bits", "--angle-steps", "--width", "--height")
    return p


def run(args) -> int:
    if args.out is None and args.show is None:
        raise UsageError("give --out DIR (write the frames), --show [DISPLAY] (show them), or both")
    if args.centre and args.show is None:
        raise UsageError("--centre only applies with --show")
    width, height, pre = args.width, args.height, None
    if args.rig is not None:
        if args.precompensate is not None:
            raise UsageError("give --rig (its light's gamma) or --precompensate GAMMA, not both")
        li = load_rig(args.rig).light
        pre = float(li.gamma)
        lw, lh = int(getattr(li, "width", 0)), int(getattr(li, "height", 0))
        if lw:
            if (width or lw, height or lh) != (lw, lh):
                raise UsageError(f"--width/--height {width or lw}x{height or lh} differ from the projector of "
                                 f"{args.rig} ({lw}x{lh})")
            width, height = lw, lh
    spec = pattern_spec_from_args(args, width or 1024, height or 768, args.center, precompensated_gamma=pre)
    names = frame_names(spec)
    if args.out is not None:
        write_frames(spec, names, args.out)
    if args.show is not None:
        show_frames(spec, names, args.show, centre=args.centre)
    return 0


def show_frames(spec: PatternSpec, names: list[str], display: str, *, centre: bool = False) -> None:
    """The frames full-screen on ``display``, stepped through by hand until q or escape."""
    frames = [render_frame(spec, n) for n in names]
    keys = ", ".join(f"{k}: {a}" for k, a in VIEWER_KEYS.items())
    print(f"showing {len(names)} {spec.codec} frame(s) on display {display} ({keys})", flush=True)
    with DisplayProjector(frames, display=display, centre=centre) as proj:
        run_viewer(proj, on_show=lambda i: print(f"  {names[i]}" if i >= 0 else "  (black)", flush=True))


def write_frames(spec: PatternSpec, names: list[str], out) -> None:
    """Every frame as <frame>.png in ``out``, plus patterns.json and frames.txt."""
    out = check_output_folder(out, what="patterns folder (--out)")
    for n in names:
        write_image(out / f"{n}.png", render_frame(spec, n))
    atomic_write_json(out / "patterns.json", spec.to_dict())
    atomic_write_bytes(out / "frames.txt", ("\n".join(f"{n}.png" for n in names) + "\n").encode())
    g = spec.precompensated_gamma
    pre = f", pre-compensated for a light gamma of {g:g}" if g != 1.0 else ""
    print(f"{len(names)} {spec.codec} frame(s) of {spec.width}x{spec.height}{pre} -> {out} "
          "(patterns.json, frames.txt)")
