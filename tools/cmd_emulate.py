"""``ringscan emulate``: run a whole virtual rig for trying captures without hardware.

Starts an emulated GRBL turntable and an emulated serial pattern projector on
pseudo-terminals and serves the virtual rig's camera on a Unix socket, prints the
ports and a ready ``ringscan capture`` command line, and runs until Ctrl-C, SIGTERM
(a service manager's stop) or ``--seconds``. The folder also gets rig.json and patterns.json for that command.
"""

from __future__ import annotations

import signal
import time
from pathlib import Path

from ringscan.hardware.emulators.rig import EmulatedRig
from ringscan.pipeline.codecs import DEFAULT_CODEC
from ringscan.pipeline.formats.atomic import atomic_write_json
from ringscan.pipeline.formats.patterns import parse_patterns
from ringscan.pipeline.formats.rig import default_rig, load_rig, rig_to_dict
from ringscan.tools.cli import add_device_option, basic_options
from ringscan.tools.cmd_capture import load_patterns

# The default pattern set: the 28-frame gray-rings set of ``ringscan patterns``'s
# defaults (7 band bits, 6 sector bits) on the default rig's 1024x768 projector.
DEFAULT_PATTERNS = {"codec": DEFAULT_CODEC, "width": 1024, "height": 768, "center": [511.5, 383.5],
                    "rho0": 8.0, "pitch": 4.0, "bits": 7, "sector_bits": 6}


def add_parser(sub):
    p = sub.add_parser("emulate", help="run an emulated rig (turntable, projector, camera) to try captures",
                       description="Emulated GRBL turntable and serial projector on pseudo-terminals plus the "
                                   "virtual rig's camera on a Unix socket; prints the ports for 'ringscan capture'.")
    p.add_argument("--rig", help="rig file (default: the default virtual rig)")
    p.add_argument("--patterns", metavar="PATTERNS.json", help="pattern set (default: 28-frame gray-rings)")
    p.add_argument("--scene", default="sphere", help="scene name or mesh file (default sphere)")
    p.add_argument("--size-mm", type=float, default=80.0, help="scene size (default 80)")
    p.add_argument("--folder", help="where the port links, camera socket, rig.json and patterns.json go "
                                    "(default: a new temporary folder)")
    p.add_argument("--flavor", choices=("grbl", "horus"), default="grbl", help="turntable firmware (default grbl)")
    p.add_argument("--time-scale", type=float, default=1.0, help="table moves this many times faster than real")
    p.add_argument("--seed", type=int, default=None, help="camera noise seed (default: fresh noise per grab)")
    p.add_argument("--seconds", type=float, default=None, help="stop after this long (default: until Ctrl-C)")
    add_device_option(p)
    basic_options(p, "--rig", "--patterns", "--scene", "--folder", "--seconds")
    return p


def _stop(signum, frame):
    raise KeyboardInterrupt


def run(args) -> int:
    # A shell starts background jobs with SIGINT ignored, and Python then keeps it ignored:
    # install the handlers so Ctrl-C (kill -INT) and SIGTERM stop the emulator cleanly either way.
    previous = {sig: signal.signal(sig, _stop) for sig in (signal.SIGINT, signal.SIGTERM)}
    try:
        return _serve(args)
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)


def _serve(args) -> int:
    rig = load_rig(args.rig) if args.rig else default_rig()
    patterns = load_patterns(args.patterns) if args.patterns else parse_patterns(DEFAULT_PATTERNS, source="default")
    emu = EmulatedRig(rig, patterns, args.scene, folder=args.folder, flavor=args.flavor, time_scale=args.time_scale,
                      seed=args.seed, size_mm=args.size_mm, device=args.device, serve_camera=True)
    try:
        folder = Path(emu.folder)
        rig_path, pat_path = folder / "rig.json", folder / "patterns.json"
        atomic_write_json(rig_path, rig_to_dict(rig))
        atomic_write_json(pat_path, patterns.to_dict())
        print(f"turntable: {emu.turntable_port}  ({emu.turntable.flavor}, on {emu.turntable.tty})", flush=True)
        print(f"projector: {emu.projector_port}  ({len(emu.projector.images)} frames, on {emu.projector.tty})",
              flush=True)
        print(f"camera:    {emu.camera_spec}", flush=True)
        print(f"try:       ringscan capture --rig {rig_path} --patterns {pat_path} --views 8 --out SCAN "
              f"--turntable {emu.turntable_port} --projector {emu.projector_port} --camera {emu.camera_spec}",
              flush=True)
        t_end = None if args.seconds is None else time.monotonic() + args.seconds
        try:
            # said inside the try: a Ctrl-C or SIGTERM sent the moment "running" is read stops it cleanly too
            print("running; Ctrl-C stops it", flush=True)
            while t_end is None or time.monotonic() < t_end:
                time.sleep(0.2 if t_end is None else max(min(0.2, t_end - time.monotonic()), 0.0))
        except KeyboardInterrupt:
            pass
    finally:
        emu.close()
    print("emulator stopped", flush=True)
    return 0
