"""``ringscan calibrate <what> ...``: calibration of a real rig (docs/calibration.md).

Sub-commands register themselves: each ``add_<name>_parser(calsub)`` of the command group
modules (``GROUPS``) adds one sub-command and sets ``_calibrate`` to its run function;
:func:`run` dispatches. The groups: ``cmd_calibrate_boards`` (camera, stereo, procam),
``cmd_calibrate_light`` (response, pose, light, latency, turntable), ``cmd_calibrate_scan``
(refine, projector-from-scan); what they share is in ``calibrate_options``.

- ``camera IMAGES...``: camera intrinsics from chessboard or ChArUco images;
- ``stereo --cam1 IMAGES... --cam2 IMAGES...``: two cameras and their pose from board image pairs;
- ``procam CAPTURE_DIR...``: camera + perspective projector from Gray-code captures;
- ``response CAPTURE_DIR...``: the projector's response curve;
- ``pose IMAGE``: the camera's pose over the reference plane from a board lying on it;
- ``light SCAN... --heights ...``: the parallel light from ring captures of a plane at known heights;
- ``turntable SCAN | IMAGES... --angles ...``: the turntable axis from a board at several table angles.
- ``latency --projector display:N --camera SPEC``: how long after a frame's swap the camera sees it in full.
- ``refine SCAN``: the extrinsics re-estimated from a scan's own matches (two cameras, or camera and projector);
- ``projector-from-scan SCAN``: the projector fitted to a two-camera scan's points (a procam rig).

New sub-commands are found by name: any module-level ``add_<name>_parser`` function of a
group is called by :func:`add_parser`, group by group, in definition order.
"""

from __future__ import annotations

import argparse

from ringscan.tools import cmd_calibrate_boards, cmd_calibrate_light, cmd_calibrate_scan
from ringscan.tools.cli import UsageError

GROUPS = (cmd_calibrate_boards, cmd_calibrate_light, cmd_calibrate_scan)
"""The modules whose ``add_<name>_parser`` functions add the sub-commands, in the order ``--help`` lists them."""


def add_parser(sub):
    p = sub.add_parser("calibrate", help="calibrate a real rig: camera, projector (procam), response",
                       description="Calibration of a real rig; see docs/calibration.md.",
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    calsub = p.add_subparsers(dest="what", metavar="WHAT")
    for group in GROUPS:
        for name, fn in list(vars(group).items()):
            if name.startswith("add_") and name.endswith("_parser") and callable(fn):
                fn(calsub)
    return p


def run(args) -> int:
    fn = getattr(args, "_calibrate", None)
    if fn is None:
        raise UsageError("calibrate: say what to calibrate (e.g. `ringscan calibrate camera --help`)")
    return int(fn(args) or 0)
