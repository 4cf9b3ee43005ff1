"""The parallel light and the turntable axis calibrated on the virtual rig, against
the truth (docs/calibration.md, sections 6 and 7).

Light: the default rig (1280x1024 camera) with a parallel light tilted 2.5 degrees
from z, turned 7 degrees about its axis, its axis pixel 15 px off the pattern
centre; the reference plane captured at z = 0 and a flat plate at z = 40 mm, with
gray-rings (7 bits, pitch 4 px, 6 sector bits) and with phase-rings (4 steps,
pitch 8 px, 6 sector bits); `calibrate_parallel_light` fits the light.

Turntable: the default rig with its turntable axis tilted 1.5 degrees and passing
through (3, -2, 0) mm; the `chessboard` scene (9x6 inner corners, 6.67 mm squares)
lying on the table, rendered under the white frame at 8 table angles over 360
degrees and at 4 angles over 90 degrees; OpenCV finds the corners, and
`calibrate_turntable` fits the axis.

The virtual rig renders with the same camera and light code as the calibration
and reconstruction use, so these figures show the fits' self-consistency.

    python benchmarks/calibration_virtual.py [--out DIR] [--device cpu]
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np

from ringscan.pipeline.calibrate.board import Board, detect_board
from ringscan.pipeline.calibrate.light import calibrate_parallel_light
from ringscan.pipeline.calibrate.turntable import axis_distance, calibrate_turntable
from ringscan.pipeline.formats.patterns import parse_patterns
from ringscan.pipeline.formats.rig import ParallelLight, Turntable, default_rig
from ringscan.pipeline.simulate import VirtualRig, make_scene, simulate_scan
from ringscan.pipeline.simulate.scenes import SceneMesh

LIGHT = ParallelLight(R=cv2.Rodrigues(np.array([0.0, 0.0, math.radians(7.0)]))[0]
                      @ cv2.Rodrigues(np.array([math.radians(2.0), math.radians(-1.5), 0.0]))[0],
                      t=np.zeros(3), pixel_pitch_mm=0.15, axis_px=np.array([520.3, 371.8]), width=1024, height=768)
AXIS = Turntable(axis_point=np.array([3.0, -2.0, 0.0]),
                 axis_dir=np.array([math.sin(math.radians(1.5)), 0.0, math.cos(math.radians(1.5))]))
HEIGHTS = (0.0, 40.0)


def plate(h: float) -> SceneMesh:
    v = np.array([[-150, -150, h], [150, -150, h], [150, 150, h], [-150, 150, h]], float)
    return SceneMesh(vertices=v, faces=np.array([[0, 1, 2], [0, 2, 3]], np.int32), name="plate")


def light_case(out: Path, codec: dict, device: str) -> None:
    rig = dataclasses.replace(default_rig(), light=LIGHT, turntable=None)
    spec = parse_patterns({"width": 1024, "height": 768, "center": [511.5, 383.5], "rho0": 8.0, "sector_bits": 6,
                           **codec})
    t0 = time.perf_counter()
    scans = [simulate_scan(out / f"{spec.codec}_z{h:g}", scene=plate(h) if h else "plane", rig=rig, patterns=spec,
                           progress=False, device=device) for h in HEIGHTS]
    t1 = time.perf_counter()
    cal = calibrate_parallel_light(scans, HEIGHTS, device=device)
    t2 = time.perf_counter()
    li = cal.light
    dR = math.degrees(float(np.linalg.norm(cv2.Rodrigues(li.R @ LIGHT.R.T)[0])))
    agree = min(c["sector_agreement"] for c in cal.captures.values())
    n = sum(c["samples"] for c in cal.captures.values())
    print(f"{spec.codec:12} axis error {np.abs(li.axis_px - LIGHT.axis_px).max():.4f} px, pitch error "
          f"{100 * abs(li.pixel_pitch_mm / LIGHT.pixel_pitch_mm - 1):.4f} %, rotation error {dR:.4f} deg "
          f"(tilt {cal.tilt_deg:.3f}, roll {cal.roll_deg:.3f}); ring RMS {cal.rms_px:.3f} px over {n} samples, "
          f"sectors agree >= {100 * agree:.1f} %; simulate {t1 - t0:.0f} s, fit {t2 - t1:.1f} s", flush=True)


def turntable_case(angles: np.ndarray, device: str) -> None:
    rig = dataclasses.replace(default_rig(), turntable=AXIS)
    board = Board(cols=9, rows=6, square=80.0 / 12.0)
    vr = VirtualRig(rig, make_scene("chessboard"), device=device)
    white = np.full((768, 1024), 255, np.uint8)
    t0 = time.perf_counter()
    views = []
    for a in angles:
        vr.set_turntable(float(a))
        views.append(detect_board(vr.render(white), board=board, name=f"{a:g}deg"))
    t1 = time.perf_counter()
    cal = calibrate_turntable(views, angles, board=board, camera=rig.camera)
    ang, dist = axis_distance(AXIS, cal.turntable)
    print(f"turntable, {len(angles)} views over {np.ptp(angles):g} deg: axis direction error {ang:.4f} deg, "
          f"position error {dist:.4f} mm (z 0..80); RMS {cal.rms_px:.3f} px; board turn vs table "
          f"<= {np.abs(cal.angle_error_deg).max():.3f} deg; render+detect {t1 - t0:.0f} s", flush=True)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", default=None, help="work folder (default: a temporary one)")
    ap.add_argument("--device", default="cpu")
    args = ap.parse_args(argv)
    out = Path(args.out or tempfile.mkdtemp(prefix="ringscan-calib-"))
    print(f"work folder {out}")
    light_case(out, {"codec": "gray-rings", "pitch": 4.0, "bits": 7}, args.device)
    light_case(out, {"codec": "phase-rings", "pitch": 8.0, "bits": 6, "steps": 4}, args.device)
    turntable_case(np.arange(0.0, 360.0, 45.0), args.device)
    turntable_case(np.arange(0.0, 91.0, 30.0), args.device)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
