"""Two cameras on the virtual rig: which rays place the points, against the truth.

Prints, for one two-camera scan of an 80 mm sphere (gray-rings + the angle code;
the test scan of tests/support/two_camera_scan.py, camera 2 turned
70 degrees about the light axis):

1. per ``--rays`` (camera-projector, camera-camera, all, auto) and for
   camera-camera with the projector uncalibrated: points, median / p95 error (mm)
   against the truth mesh, coverage, median residual, the calibration check;
2. the same scan with the rig file's camera-1-to-camera-2 rotation off by 2
   degrees: the epipolar check (it warns) and the camera-camera error;
3. the predicted match sigmas against the matches' actual errors: each match's
   camera-2 position against the truth (camera 1's truth depth at uv1, bilinear,
   projected into camera 2) over sqrt(sigma1^2 + sigma2^2), per axis: its MAD
   (1.4826 x median absolute deviation; 1 where the prediction is honest) and
   the shares within 1 and 2 predicted sigmas (0.68 and 0.95 for a Gaussian);
   the same for two ``decoded`` two-camera scans of the sphere made from the
   truth (every pixel's projector coordinate as an imported Gray code gives it:
   integer codes, and exact codes in the codec's 1/32 px);
4. the same sphere under phase-rings (the same rings and angle code, 4 fringe steps): camera-camera,
   camera-camera with camera 1's code error stood in isotropically on camera 1 (before 2026-12-08, when
   such codes went through the matcher's map as ring edges do), and all three rays.

Each row of 1 and 4 has the points' median abs(e)/sigma and share beyond 3 sigma (``ringscan evaluate``'s).

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
from tests.support.two_camera_scan import ANGLE_PATTERNS, simulate_two_camera_scan  # noqa: E402


HEADER = ("| rays | points | median mm | p95 mm | coverage | median residual | calibration check (median / p95) | "
          "median abs(e)/sigma | beyond 3 sigma |\n|---|---|---|---|---|---|---|---|---|")
PHASE_PATTERNS = {**ANGLE_PATTERNS, "codec": "phase-rings", "steps": 4}
"""The test scan's patterns as phase-rings (the same rings' pitch, sectors and angle code, 4 fringe steps)."""


def _row(name, rep, ev):
    v = rep["views"][0]
    c = v.get("calibration_check", {})
    a = ev["all"]
    sg = a.get("sigma") or {}
    print(f"| {name} | {v['points']} | {a['median_mm']:.4f} | {a['p95_mm']:.4f} | "
          f"{100 * ev['views']['view_000']['coverage']:.1f} % | {v.get('median_residual') or 0:.3f} | "
          f"{c.get('kind', '-')} {c.get('median_px', float('nan')):.3f} / {c.get('p95_px', float('nan')):.3f} px | "
          f"{sg.get('median_ratio', float('nan')):.2f} | {100 * sg.get('beyond_3', float('nan')):.1f} % |")


def _phase_rings(work: Path) -> None:
    """The same sphere under phase-rings: camera to camera through the matcher's map (the default since
    2026-12-08), the same with camera 1's code error stood in isotropically on camera 1 (as before), and all
    three rays."""
    from ringscan.pipeline.codecs.phase_rings import PhaseRingsCodec

    folder = work / "scan_phase"
    if not (folder / "scan.json").is_file():
        shutil.rmtree(folder, ignore_errors=True)
        simulate_two_camera_scan(folder, patterns=PHASE_PATTERNS)
    scan = load_scan(folder)
    print()
    print("phase-rings, the same sphere:")
    print(HEADER)
    for name, rays, stand_in in (("camera-camera", "camera-camera", False),
                                 ("camera-camera, code error stood in on camera 1 (before)", "camera-camera", True),
                                 ("all", "all", False)):
        out = work / f"rec_phase_{rays}{'_stand_in' if stand_in else ''}"
        PhaseRingsCodec.isotropic_code_error = stand_in  # (a class attribute over the base's property)
        try:
            rep = reconstruct_scan(scan, out, settings=ReconstructSettings(stereo=StereoSettings(rays=rays)),
                                   progress=False)
        finally:
            del PhaseRingsCodec.isotropic_code_error
        _row(name, rep, evaluate_recon(out, scan))


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
    print(HEADER)
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
    _sigma_honesty(scan)
    from tests.support.two_camera_scan import simulate_decoded_two_camera_scan

    for integer in (True, False):
        dec = work / ("decoded_integer" if integer else "decoded_exact")
        if not (dec / "scan.json").is_file():
            shutil.rmtree(dec, ignore_errors=True)
            simulate_decoded_two_camera_scan(dec, integer=integer)
        print(f"decoded two-camera scan, {'integer' if integer else 'exact (1/32 px)'} codes:", end="")
        _sigma_honesty(load_scan(dec))
    _phase_rings(work)
    return 0


def _sigma_honesty(scan) -> None:
    """Actual match errors (camera-2 px, against the truth) over their predicted sigmas."""
    from ringscan.pipeline.reconstruct.stereo import match_view
    from tests.support.two_camera_scan import true_uv2

    m = match_view(scan, scan.views[0], device="cpu")
    keep, uv2 = true_uv2(scan, m)
    e = m.uv2[keep] - uv2
    pred = np.hypot(m.sigma1, m.sigma2)[keep]
    zn = e / pred[:, None]
    mad = [1.4826 * float(np.median(np.abs(zn[:, k] - np.median(zn[:, k])))) for k in (0, 1)]
    print()
    print("Predicted match sigmas (camera-2 px): error / sqrt(sigma1^2 + sigma2^2), per axis")
    print(f"  {int(keep.sum())} matches; median |error| {np.median(np.hypot(e[:, 0], e[:, 1])):.4f} px; median "
          f"sigma1 {np.median(m.sigma1):.4f}, sigma2 {np.median(m.sigma2):.4f} px")
    print(f"  MAD x {mad[0]:.2f}, y {mad[1]:.2f} (1 if honest); within 1 sigma {np.mean(np.abs(zn) < 1):.2f} (0.68), "
          f"within 2 sigma {np.mean(np.abs(zn) < 2):.2f} (0.95)")


if __name__ == "__main__":
    raise SystemExit(main())
