"""Two cameras on the virtual rig: which rays place the points, against the truth.

Prints, for one two-camera scan of an 80 mm sphere (gray-rings + the angle code;
the test scan of tests/pipeline/reconstruct/two_camera_scan.py, camera 2 turned
70 degrees about the light axis):

1. per ``--rays`` (camera-projector, camera-camera, all, auto) and for
   camera-camera with the projector uncalibrated: points, median / p95 error (mm)
   against the truth mesh, coverage, median residual, the calibration check;
2. the same scan with the rig file's camera-1-to-camera-2 rotation off by 2
   degrees: the epipolar check (it warns) and the camera-camera error.

Usage::

    python benchmarks/stereo_rays.py [--work DIR]
"""

from __future__ import annotations

import argparse
import dataclasses
import shutil
import sys
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from ringscan.pipeline.evaluate.metrics import evaluate_recon  # noqa: E402
from ringscan.pipeline.formats.rig import UncalibratedLight  # noqa: E402
from ringscan.pipeline.formats.scan import load_scan, save_scan  # noqa: E402
from ringscan.pipeline.reconstruct.scan import reconstruct_scan  # noqa: E402
from ringscan.pipeline.reconstruct.settings import ReconstructSettings, StereoSettings  # noqa: E402
from tests.pipeline.reconstruct.two_camera_scan import simulate_two_camera_scan  # noqa: E402


def _row(name, rep, ev):
    v = rep["views"][0]
    c = v.get("calibration_check", {})
    a = ev["all"]
    print(f"| {name} | {v['points']} | {a['median_mm']:.4f} | {a['p95_mm']:.4f} | "
          f"{100 * ev['views']['view_000']['coverage']:.1f} % | {v.get('median_residual') or 0:.3f} | "
          f"{c.get('kind', '-')} {c.get('median_px', float('nan')):.3f} / {c.get('p95_px', float('nan')):.3f} px |")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--work", default="/tmp/ringscan_stereo_rays", help="work folder (scans kept for reruns)")
    args = ap.parse_args()
    work = Path(args.work)
    folder = work / "scan"
    if not (folder / "scan.json").is_file():
        shutil.rmtree(work, ignore_errors=True)
        work.mkdir(parents=True)
        simulate_two_camera_scan(folder)
    scan = load_scan(folder)
    print("| rays | points | median mm | p95 mm | coverage | median residual | calibration check (median / p95) |")
    print("|---|---|---|---|---|---|---|")
    for rays in ("camera-projector", "camera-camera", "all", "auto"):
        out = work / f"rec_{rays}"
        rep = reconstruct_scan(scan, out, settings=ReconstructSettings(stereo=StereoSettings(rays=rays)),
                               progress=False)
        _row(rays, rep, evaluate_recon(out, scan))
    # the projector uncalibrated: camera-camera only (evaluated against the calibrated twin's truth)
    unc = work / "scan_uncalibrated"
    if not (unc / "scan.json").is_file():
        shutil.copytree(folder, unc)
        s = load_scan(unc)
        li = s.rig.light
        save_scan(dataclasses.replace(s, rig=dataclasses.replace(
            s.rig, light=UncalibratedLight(width=li.width, height=li.height, gamma=li.gamma)), rig_ref=None))
    rep = reconstruct_scan(load_scan(unc), work / "rec_uncalibrated", progress=False)
    _row("camera-camera, projector uncalibrated", rep, evaluate_recon(work / "rec_uncalibrated", scan))
    # a rig file whose camera-1-to-camera-2 rotation is 2 degrees off
    rig = scan.rig
    c1, c2 = rig.camera, rig.camera2
    R_rel = c2.R @ c1.R.T
    T_rel = c2.t - R_rel @ c1.t
    R_bad = cv2.Rodrigues(np.array([0.0, np.radians(2.0), 0.0]))[0] @ R_rel
    bad = dataclasses.replace(scan, rig=dataclasses.replace(
        rig, camera2=dataclasses.replace(c2, R=R_bad @ c1.R, t=R_bad @ c1.t + T_rel)))
    rep = reconstruct_scan(bad, work / "rec_rotated", settings=ReconstructSettings(
        stereo=StereoSettings(rays="camera-camera")), progress=False)
    _row("camera-camera, rig rotated 2 deg (warns)", rep, evaluate_recon(work / "rec_rotated", scan))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
