"""``ringscan capture``: capture a scan from a rig (a real one, or the emulated virtual rig).

::

    ringscan capture --rig RIG --patterns PATTERNS.json --views N --out SCAN
                     --turntable PORT --projector PORT --camera SPEC
    ringscan capture ... --projector display:1 --camera SPEC   (a projector plugged in as a screen)
    ringscan capture --rig RIG --patterns PATTERNS.json --views N --out SCAN --virtual SCENE
    ringscan capture --out SCAN --resume [device options as before] [--table-at DEG]

The frames go to SCAN/view_<k>/<frame>.png as they are grabbed, scan.json is
rewritten after each one, capture.json keeps the plan, the settings and the
table's angle; ``--resume`` continues an interrupted capture. Ctrl-C always stops
it (exit status 130), even when Python swallowed the interrupt in a finalizer. See
docs/hardware.md.
"""

from __future__ import annotations

import argparse
import dataclasses
import logging
from pathlib import Path

from ringscan.hardware.capture.latency import read_rig_latency
from ringscan.hardware.capture.plan import CapturePlan, check_angles, plan_capture
from ringscan.hardware.capture.sequence import (
    MAX_VIEWS,
    CaptureSettings,
    InterruptGuard,
    capture_scan,
    read_capture_state,
)
from ringscan.hardware.capture.session import run_session, wait_for_key, wait_for_serial
from ringscan.hardware.devices.camera import open_camera
from ringscan.hardware.devices.display import DisplayProjector, parse_display_spec
from ringscan.hardware.devices.grbl import GrblTurntable
from ringscan.hardware.devices.projector import SerialProjector
from ringscan.hardware.devices.turntable import VirtualTurntable
from ringscan.hardware.emulators.rig import EmulatedRig
from ringscan.hardware.errors import CaptureError
from ringscan.pipeline.codecs.render import render_frame
from ringscan.pipeline.formats.atomic import read_json
from ringscan.pipeline.formats.patterns import PatternSpec, frame_names, parse_patterns
from ringscan.pipeline.formats.rig import load_rig
from ringscan.pipeline.formats.scan import load_scan
from ringscan.tools.cli import UsageError, add_device_option, basic_options, check_frame_bits_option

log = logging.getLogger(__name__)

SESSION_POSES = ("upright", "upside-down", "side-x", "side-y", "tetra-1", "tetra-2", "tetra-3")
"""Default resting poses of the virtual scene in a session (``--virtual-poses``)."""

# Option -> CaptureSettings field.
SETTING_OPTIONS = {
    "turntable_settle": "turntable_settle_s",
    "projector_settle": "projector_settle_s",
    "feed": "feed_deg_per_min",
    "timeout": "command_timeout_s",
    "motion_timeout": "motion_timeout_s",
    "retries": "retries",
    "retry_delay": "retry_delay_s",
    "image_format": "image_format",
}


def load_patterns(path) -> PatternSpec:
    """A pattern set from a JSON file: a ``patterns`` block (``ringscan patterns`` writes
    patterns.json) or any JSON object holding one under ``"patterns"`` (a scan.json)."""
    d = read_json(path)
    if "codec" not in d and isinstance(d.get("patterns"), dict):
        d = d["patterns"]
    return parse_patterns(d, source=path)


def add_parser(sub):
    p = sub.add_parser(
        "capture", help="capture a scan from a turntable rig (or the emulated virtual rig)",
        description="For each view turn the table and settle; for each frame show it, wait for the projector's "
                    "acknowledgement and the settle time, grab, write the frame and scan.json atomically. "
                    "--resume continues an interrupted capture; a device fault is retried, then the capture stops "
                    "with a valid partial scan.")
    _add_scan_options(p)
    _add_device_options(p.add_argument_group("devices"))
    _add_virtual_options(p.add_argument_group("virtual rig"))
    _add_settings_options(
        p.add_argument_group("settings (defaults: --capture-settings file, else the resumed capture's, else built in)"))
    basic_options(p, "--rig", "--patterns", "--views", "--resume", "--turntable", "--projector", "--camera",
                  "--exposure", "--virtual")
    return p


def _add_scan_options(p):
    """What to capture and where: the scan folder, rig, patterns and views, resuming, live
    reconstruction and capture sessions of several poses."""
    p.add_argument("--out", required=True, metavar="SCAN",
                   help="scan folder (new or empty; the interrupted one with --resume)")
    p.add_argument("--rig", help="rig (calibration) file (required for a new capture)")
    p.add_argument("--patterns", metavar="PATTERNS.json",
                   help="pattern set, as 'ringscan patterns' writes it (required for a new capture)")
    p.add_argument("--views", type=int, metavar="N", help="number of turntable views (required for a new capture)")
    p.add_argument("--step", type=float, default=None, metavar="DEG", help="angle between views (default 360/views)")
    p.add_argument("--start", type=float, default=None, metavar="DEG", help="angle of the first view (default 0)")
    p.add_argument("--resume", action="store_true", help="continue the interrupted capture in --out")
    p.add_argument("--table-at", type=float, default=None, metavar="DEG",
                   help="with --resume: the angle the table stands at now (needed when its angle is unknown: a "
                        "move cut short, an alarm, a table found turning)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.add_argument("--reconstruct", metavar="DIR", default=None,
                   help="reconstruct each view into DIR (as `ringscan reconstruct`) while the next one is captured")
    p.add_argument("--reconstruct-settings", metavar="JSON", default=None,
                   help="reconstruction settings file for --reconstruct (as `ringscan reconstruct --settings`)")
    p.add_argument("--poses", type=int, default=None, metavar="N",
                   help="a capture session: N poses of one object in a row into --out/pose_<i> (the user turns "
                        "the object over between poses), each reconstructed live into --out/recon/pose_<i>, then "
                        "all fused into one mesh in --out/mesh; rerun to resume (see docs/batch.md)")
    p.add_argument("--trigger", default="key", metavar="key|PORT",
                   help="with --poses: how the user says the next pose is ready: Enter on stdin (key, default) or "
                        "a line on a serial port (PORT)")
    p.add_argument("--max-pose-rmse", type=float, default=None, metavar="MM",
                   help="with --poses: largest point-to-plane RMSE of a pose's alignment (as `ringscan fuse`; "
                        "default 0.15 mm; coarse cameras need more)")
    p.add_argument("--virtual-poses", default=None, metavar="POSE,...",
                   help="with --poses and --virtual: the scene's resting pose for each pose (as `ringscan simulate "
                        "--pose`; default upright, upside-down, side-x, side-y, ...)")


def _add_device_options(g):
    """The real devices: turntable, projector and camera, their ports and the camera's controls."""
    g.add_argument("--turntable", metavar="PORT", help="GRBL/Horus turntable serial port (or pyserial URL); "
                                                       "may be left out for a single view")
    g.add_argument("--projector", metavar="PORT", help="pattern projector serial port (or pyserial URL), or "
                                                       "display[:N|:NAME] for a projector plugged in as a screen "
                                                       "(waits the rig's light.latency_s after each frame)")
    g.add_argument("--centre", action="store_true", help="display projector: show frames smaller than the display "
                                                         "centred (else a size mismatch is an error)")
    g.add_argument("--camera", metavar="SPEC", help="camera: OpenCV index (0), URL, video or image-sequence "
                                                    "path, folder:SCAN (replay), unix:SOCKET (ringscan emulate)")
    g.add_argument("--baud", type=int, default=115200, help="serial baud rate of both boards (default 115200)")
    g.add_argument("--direction", type=int, choices=(1, -1), default=1,
                   help="-1 if positive G-code X turns the object clockwise seen from above (default 1)")
    g.add_argument("--exposure", type=float, default=None, metavar="E", help="manual camera exposure (backend units)")
    g.add_argument("--gain", type=float, default=None, metavar="G", help="camera gain (backend units)")
    g.add_argument("--allow-auto-exposure", action="store_true",
                   help="go on when the camera cannot switch auto exposure off (--exposure is then only a "
                        "starting value; frames may be re-levelled between white and black)")
    g.add_argument("--flush", type=int, default=None, metavar="N",
                   help="frames dropped before each grab (default 4 for live cameras, 0 for files)")
    g.add_argument("--frame-bits", type=int, default=None, metavar="N",
                   help="bits the camera's 16-bit frames hold (10, 12: values 0..1023, 0..4095), written as "
                        "scan.json's frame_bits so that they are read scaled to 16 bits (docs/formats.md); every "
                        "frame is checked against it (default: the frames' own bits)")


def _add_virtual_options(v):
    """The emulated virtual rig in place of the devices."""
    v.add_argument("--virtual", metavar="SCENE", help="capture from the emulated virtual rig: turntable and "
                                                      "projector emulated on pseudo-terminals, camera rendered "
                                                      "(scene name or mesh file)")
    v.add_argument("--size-mm", type=float, default=80.0, metavar="MM", help="virtual scene size (default 80)")
    v.add_argument("--seed", type=int, default=0, help="virtual camera noise seed (default 0)")
    v.add_argument("--flavor", choices=("grbl", "horus"), default="grbl", help="emulated turntable firmware")
    v.add_argument("--time-scale", type=float, default=100.0, metavar="X",
                   help="emulated table moves this many times faster than a real one (default 100)")
    add_device_option(v)


def _add_settings_options(s):
    """The capture settings (CaptureSettings): a settings file and one option per timing or retry setting."""
    s.add_argument("--capture-settings", dest="settings", metavar="JSON",
                   help="capture settings file (keys of CaptureSettings; --reconstruct-settings is the "
                        "reconstruction's)")
    # The old spelling, hidden: --settings is the reconstruction's settings in reconstruct and batch.
    s.add_argument("--settings", dest="settings", help=argparse.SUPPRESS)
    s.add_argument("--turntable-settle", type=float, metavar="S", help="wait after a move, s (default 0.5; 0 virtual)")
    s.add_argument("--projector-settle", type=float, metavar="S", help="wait after a frame's ack, s (default 0.05; 0 virtual)")
    s.add_argument("--feed", type=float, metavar="DEG_PER_MIN", help="table speed, deg/min (default 600)")
    s.add_argument("--timeout", type=float, metavar="S", help="reply timeout, s (default 2)")
    s.add_argument("--motion-timeout", type=float, metavar="S", help="extra time allowed per move, s (default 30)")
    s.add_argument("--retries", type=int, metavar="N", help="retries of a failed device operation (default 3)")
    s.add_argument("--retry-delay", type=float, metavar="S", help="pause before a retry, s (default 0.5)")
    s.add_argument("--image-format", "--frames", dest="image_format", choices=("png", "tiff", "packed"),
                   help="frame files (default png; tiff: uncompressed, 2.3x the space, ~4x faster to read; packed: "
                        "one frame store per view, frames appended as they arrive, about the PNGs' size)")


def _settings(args, out: Path) -> CaptureSettings:
    if args.settings:
        base = CaptureSettings.from_dict(read_json(args.settings), source=args.settings)
    elif args.resume and (out / "capture.json").is_file() and read_capture_state(out).get("settings"):
        base = CaptureSettings.from_dict(read_capture_state(out)["settings"], source=out / "capture.json")
    elif args.virtual:
        base = CaptureSettings(turntable_settle_s=0.0, projector_settle_s=0.0)
    else:
        base = CaptureSettings()
    over = {field: getattr(args, opt) for opt, field in SETTING_OPTIONS.items() if getattr(args, opt) is not None}
    return dataclasses.replace(base, **over) if over else base


def run(args) -> int:
    with InterruptGuard():  # a Ctrl-C swallowed in a finalizer still ends the command (exit 130)
        if args.poses is not None:
            return _run_session(args)
        if args.virtual_poses or args.trigger != "key":
            raise UsageError("--trigger and --virtual-poses only apply with --poses")
        return _run(args)


def _run_session(args) -> int:
    """``--poses N``: capture N poses (hardware.capture.session), reconstruct each live, fuse them into one mesh."""
    if args.poses < 1:
        raise UsageError(f"--poses {args.poses}: expected 1 or more")
    if args.reconstruct or args.resume or args.table_at is not None:
        raise UsageError("--poses reconstructs into --out/recon and resumes by itself: no --reconstruct, --resume "
                         "or --table-at")
    session = Path(args.out)
    if session.exists() and not session.is_dir():
        raise ValueError(f"{session}: exists and is not a folder (the session folder)")
    poses = args.virtual_poses.split(",") if args.virtual_poses else list(SESSION_POSES)[:args.poses]
    if args.virtual_poses and not args.virtual:
        raise UsageError("--virtual-poses only applies with --virtual")
    if args.virtual and len(poses) < args.poses:
        raise UsageError(f"--virtual-poses: {len(poses)} poses given for --poses {args.poses}")
    scene = None
    if args.virtual:
        from ringscan.pipeline.simulate.scenes import make_scene, pose_scene

        base = make_scene(args.virtual, size_mm=args.size_mm)
        scene = [pose_scene(base, p)[0] for p in poses[:args.poses]]
    recon = session / "recon"

    def capture_pose(i: int, folder: Path, resume: bool) -> None:
        one = argparse.Namespace(**{**vars(args), "out": str(folder), "resume": resume,
                                    "reconstruct": str(recon / folder.name), "poses": None})
        if scene is not None:
            one.virtual = scene[i]
        if _run(one) != 0:
            raise CaptureError(f"pose {i}: the live reconstruction into {recon / folder.name} failed")

    wait = wait_for_key if args.trigger == "key" else wait_for_serial(args.trigger, baudrate=args.baud)
    folders = run_session(session, args.poses, capture_pose, wait=wait,
                          labels=poses[:args.poses] if args.virtual else None)
    from ringscan.pipeline.fusion.poses import PoseSettings
    from ringscan.pipeline.fusion.workflow import fuse_and_mesh

    ps = PoseSettings() if args.max_pose_rmse is None else PoseSettings(max_rmse_mm=args.max_pose_rmse)
    rep = fuse_and_mesh([recon / f.name for f in folders], session / "mesh", device=args.device, preview=False,
                        pose_settings=ps)
    print(f"fused {args.poses} pose(s): {rep['fusion'].get('points', '?')} points -> {session / 'mesh'}")
    return 0


def _run(args) -> int:
    check_angles(table_at=args.table_at, start=args.start, step=args.step)
    out = Path(args.out)
    rig = load_rig(args.rig) if args.rig else None
    patterns = load_patterns(args.patterns) if args.patterns else None
    _check_options(args, rig, patterns)
    settings, display = _capture_settings(args, out)
    live = _live_reconstructor(args)
    plan = plan_capture(out, rig=rig, patterns=patterns, views=args.views, resume=args.resume,
                        table_at=args.table_at, virtual=bool(args.virtual))
    names = frame_names(plan.patterns)
    devices = _Devices()
    try:
        devices.open(args, plan, settings=settings, display=display, names=names)
        scan = capture_scan(out, camera=devices.camera, projector=devices.projector, turntable=devices.turntable,
                            rig=rig, patterns=patterns, views=args.views, step_deg=args.step, start_deg=args.start,
                            settings=settings, resume=args.resume, table_at=plan.table_at,
                            progress=not args.no_progress, on_view=live, frame_bits=args.frame_bits)
    except CaptureError:
        if live is not None:  # keep what was captured reconstructed, then report the fault
            try:
                live.finish(load_scan(out, check_files=False, allow_incomplete=True))
            except Exception as e:  # noqa: BLE001 - the capture's fault is the error to report
                log.warning("reconstructing the partial scan failed: %s", e)
        raise
    finally:
        devices.close()
    print(f"captured {len(scan.views)} view(s) x {len(names)} frame(s) -> {out}")
    return 0 if live is None else _finish_live(args, out, live, scan)


def _check_options(args, rig, patterns: PatternSpec | None) -> None:
    """Options that only go together, refused before anything is opened."""
    if not args.resume and (rig is None or patterns is None or args.views is None):
        raise UsageError("a new capture needs --rig, --patterns and --views (or --resume to continue one)")
    if args.views is not None and not 1 <= args.views <= MAX_VIEWS:  # before: 10^9 views planned in memory
        raise UsageError(f"--views: expected 1 to {MAX_VIEWS} views (a view every 0.036 degrees), got {args.views}")
    if args.table_at is not None and not args.resume:
        raise UsageError("--table-at only applies with --resume")
    if args.reconstruct_settings and not args.reconstruct:
        raise UsageError("--reconstruct-settings only applies with --reconstruct")
    if args.allow_auto_exposure and args.exposure is None:
        raise UsageError("--allow-auto-exposure only applies with --exposure")
    check_frame_bits_option(args.frame_bits)


def _capture_settings(args, out: Path):
    """The capture settings and the display spec (None: a serial projector)."""
    settings = _settings(args, out)
    display = parse_display_spec(args.projector) if args.projector else None
    if display is not None and args.rig and args.projector_settle is None and read_rig_latency(args.rig) > 0:
        # the projector's measured latency (ringscan calibrate latency) is the wait after each frame
        settings = dataclasses.replace(settings, projector_settle_s=read_rig_latency(args.rig))
    if args.centre and display is None:
        raise UsageError("--centre only applies with --projector display[:N]")
    return settings, display


def _live_reconstructor(args):
    """``--reconstruct``: the reconstructor fed each view as it is captured (None without it)."""
    if not args.reconstruct:
        return None
    from ringscan.pipeline.reconstruct.live import LiveReconstructor
    from ringscan.tools.cmd_reconstruct import load_settings

    return LiveReconstructor(args.reconstruct, settings=load_settings(args.reconstruct_settings), device=args.device)


class _Devices:
    """The devices of one capture, opened one after the other; :meth:`close` closes whichever
    were opened, also when opening one of them failed."""

    def __init__(self):
        self.emu = self.camera = self.projector = self.turntable = None

    def open(self, args, plan: CapturePlan, *, settings: CaptureSettings, display, names: list[str]) -> None:
        if args.virtual:
            if args.turntable or args.projector or args.camera:
                raise UsageError("--virtual replaces --turntable, --projector and --camera")
            self.emu = EmulatedRig(plan.rig, plan.patterns, args.virtual, flavor=args.flavor,
                                   time_scale=args.time_scale, start_deg=plan.table_deg, seed=args.seed,
                                   size_mm=args.size_mm, device=args.device)
            tt_port, pj_port = self.emu.turntable_port, self.emu.projector_port
            self.camera = self.emu.camera
        else:
            missing = [o for o, v in (("--projector", args.projector), ("--camera", args.camera)) if not v]
            if not args.turntable and plan.views > 1:
                missing.insert(0, "--turntable")
            if missing:
                raise UsageError(f"missing {', '.join(missing)} (or use --virtual SCENE for the emulated rig)")
            tt_port, pj_port = args.turntable, args.projector
            self.camera = open_camera(args.camera, flush_frames=args.flush, exposure=args.exposure, gain=args.gain,
                                      allow_auto_exposure=args.allow_auto_exposure)
        if tt_port:
            self.turntable = GrblTurntable(tt_port, baudrate=args.baud, feed_deg_per_min=settings.feed_deg_per_min,
                                           direction=args.direction, timeout_s=settings.command_timeout_s,
                                           motion_timeout_s=settings.motion_timeout_s, position_deg=plan.table_deg)
        else:
            self.turntable = VirtualTurntable(plan.table_deg)  # one view: nothing turns
        if display is not None:
            self.projector = DisplayProjector([render_frame(plan.patterns, n) for n in names], display=display,
                                              centre=args.centre)
        else:
            self.projector = SerialProjector(pj_port, baudrate=args.baud, timeout_s=settings.command_timeout_s,
                                             expect_names=names)

    def close(self) -> None:
        for dev in (self.turntable, self.projector, self.camera, self.emu):
            if dev is not None:
                try:
                    dev.close()
                except Exception as e:  # closing must not hide the real error
                    log.warning("closing %s failed: %s", type(dev).__name__, e)


def _finish_live(args, out: Path, live, scan) -> int:
    """Reconstruct the views the live reconstructor has not done yet; 1 if it failed."""
    rep = live.finish(scan)
    if rep is None:
        log.error("%s; run `ringscan reconstruct %s --out %s --resume` once the cause is fixed", live.error, out,
                  args.reconstruct)
        return 1
    t = rep["totals"]
    print(f"reconstructed {len(rep['views'])} view(s): {t['points']} points -> {args.reconstruct}")
    return 0
