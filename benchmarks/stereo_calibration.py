"""Calibration from a scan's matches: refine and projector-from-scan, against known truth.

1. Virtual rig (the numbers of ../shared/data/rigs/oblique_projector.json and a
   second camera mirrored across the projector axis, tests/support/
   stereo_truth.py): a wavy surface seen by both cameras and the projector,
   exact pixels plus Gaussian noise (``--noise`` px per coordinate).
   - refine, camera 2 against camera 1, from a rig whose camera 2 is turned by
     2 deg: epipolar distance, reprojection error, pose error and the median 3D
     error of the two-camera points against the truth, for the turned rig, the
     refined one and the true one;
   - refine, camera against the projector, the same with camera 1 turned;
   - projector-from-scan: the projector fitted to the points the two (true)
     cameras triangulate: intrinsics error (%), pose error (deg, mm), RMS, the
     fit's standard deviations and condition;
   - refine --pair projector of the two-camera rig, from a projector turned by
     2 deg (20000 matches): camera 1 and the projector alone, and with camera 2
     held as the third device: the projector's rotation and centre error.
2. Real captures (../shared/data/procam, when present): the three captures
   imported (``decoded`` scan); refine (camera against the projector) from the
   calibration published with the data and from a fresh ``calibrate procam`` of the
   same captures: epipolar distance before and after.
3. A virtual two-camera scan (tests/support/two_camera_scan.py: a
   320x256 camera pair 70 deg apart around an 80 mm sphere on the reference plane,
   the default rig's perspective projector, rings + angle) matched by ``match_view``:
   refine from camera 2 turned by 2 deg, and projector-from-scan from the true and
   from the refined rig; the 3D error is the median distance of the two-camera
   points from the sphere or the plane, whichever is nearer.

   ``--ring-curvature on|off``: decoded with ``SampleSettings.ring_curvature`` on (the default, as the
   calibrate commands do) or off.

    python benchmarks/stereo_calibration.py [--noise 0.1 0.3] [--points 200000] [--data DIR] [--no-scan]
    python benchmarks/stereo_calibration.py --scan-only [--ring-curvature on|off]   # section 3 alone
"""

from __future__ import annotations

import argparse
import contextlib
import io
import math
import sys
import tempfile
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np

from ringscan.pipeline.calibrate.projector_fit import decoded_pairs, fit_projector, triangulation_covariance
from ringscan.pipeline.calibrate.rig_refine import (
    refine_extrinsics,
    relative_pose,
    rotation_angle_deg,
    triangulate_pair,
)
from ringscan.pipeline.formats.rig import load_rig
from ringscan.pipeline.formats.scan import load_scan

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # the repository: tests.support
from tests.support.stereo_truth import oblique_devices, observe  # noqa: E402


def turned(dev, deg: float):
    rv = np.array([0.3, -0.8, 0.5])
    rv *= math.radians(deg) / np.linalg.norm(rv)
    Rd, _ = cv2.Rodrigues(rv)
    return replace(dev, R=Rd @ dev.R, t=Rd @ dev.t)


def points_error(dev1, R, t, u1, u2, X_true, dev2) -> float:
    """Median 3D error (mm) of the pair's points triangulated with relative pose (R, t), world frame of dev1."""
    n1 = cv2.undistortPoints(u1.reshape(-1, 1, 2), dev1.K, dev1.dist).reshape(-1, 2)
    n2 = cv2.undistortPoints(u2.reshape(-1, 1, 2), dev2.K, dev2.dist).reshape(-1, 2)
    Xc = triangulate_pair(R, t, n1, n2)
    Xw = (Xc - dev1.t) @ dev1.R
    return float(np.median(np.linalg.norm(Xw - X_true, axis=1)))


def pose_error(R, t, Rt, tt) -> tuple[float, float]:
    return rotation_angle_deg(R @ Rt.T), float(np.linalg.norm(t - tt))


def refine_row(label, dev1, dev2, u1, u2, X, *, moved: str):
    """Turn ``moved`` ('2' or '1') by 2 deg, refine, print before / after / truth."""
    Rt, tt = relative_pose(dev1, dev2)
    d1, d2 = (dev1, turned(dev2, 2.0)) if moved == "2" else (turned(dev1, 2.0), dev2)
    ref = refine_extrinsics(d1, d2, u1, u2)
    true = refine_extrinsics(dev1, dev2, u1, u2)  # its "before" is the true rig's residual
    print(f"  {label}: {ref.used} matches used")
    for name, R, t, epi, rep in (("turned 2 deg", ref.R0, ref.t0, ref.epipolar_before, ref.reprojection_before),
                                 ("refined", ref.R, ref.t, ref.epipolar_after, ref.reprojection_after),
                                 ("true rig", Rt, tt, true.epipolar_before, true.reprojection_before)):
        de, dt = pose_error(R, t, Rt, tt)
        # points in device 1's true frame: the refined pose is relative, so measure in device 1's frame
        e3 = points_error(dev1, R, t, u1, u2, X, dev2)
        print(f"    {name:13s} epipolar median {epi.median_px:8.3f} p95 {epi.p95_px:8.3f} px | reprojection RMS "
              f"{rep.rms_px:8.3f} px | pose error {de:7.4f} deg {dt:7.3f} mm | 3D median error {e3:8.3f} mm")


def synthetic(noise: float, n: int) -> None:
    X, u1, u2, up = observe(n, noise_px=noise, seed=11)
    cam1, cam2, proj = oblique_devices()
    print(f"virtual rig, {len(X)} points, noise {noise:g} px per coordinate")
    refine_row("refine camera 2 against camera 1", cam1, cam2, u1, u2, X, moved="2")
    refine_row("refine camera 1 against the projector", cam1, proj, u1, up, X, moved="1")
    R, t = relative_pose(cam1, cam2)
    n1 = cv2.undistortPoints(u1.reshape(-1, 1, 2), cam1.K, cam1.dist).reshape(-1, 2)
    n2 = cv2.undistortPoints(u2.reshape(-1, 1, 2), cam2.K, cam2.dist).reshape(-1, 2)
    Xw = (triangulate_pair(R, t, n1, n2) - cam1.t) @ cam1.R
    fit = fit_projector(Xw, up, size=(proj.width, proj.height))
    K, Kt = fit.light.K, proj.K
    print(f"  projector-from-scan: RMS {fit.rms_px:.3f} px over {fit.used} points; "
          f"fx {100 * (K[0, 0] / Kt[0, 0] - 1):+.3f} %, fy {100 * (K[1, 1] / Kt[1, 1] - 1):+.3f} %, "
          f"cx {K[0, 2] - Kt[0, 2]:+.2f} px, cy {K[1, 2] - Kt[1, 2]:+.2f} px, "
          f"k1 {fit.light.dist[0] - proj.dist[0]:+.4f}, k2 {fit.light.dist[1] - proj.dist[1]:+.4f}; "
          f"pose {rotation_angle_deg(fit.light.R @ proj.R.T):.4f} deg, "
          f"{np.linalg.norm(fit.light.center - proj.center):.3f} mm")
    print(f"    fit's own std: fx {fit.std['fx']:.3f} px, cx {fit.std['cx']:.3f} px, cy {fit.std['cy']:.3f} px, "
          f"rotation {fit.std['rotation_deg']:.4f} deg, position {fit.std['position']:.3f} mm; condition "
          f"{fit.condition:.3g}; problems: {fit.problems or 'none'}")
    print(f"    residual correlation {fit.correlation:.2f}x; distortion: {'; '.join(fit.decisions)}")


def projector_of_two_cameras(noise: float) -> None:
    """refine --pair projector on the two-camera rig: two views, and camera 2 held as the third device."""
    from ringscan.pipeline.calibrate.rig_refine import refine_procam_rig
    from ringscan.pipeline.formats.rig import Rig, Volume

    cam1, cam2, proj = oblique_devices()
    _, u1, u2, up = observe(20000, noise_px=noise, seed=5)
    rig = Rig(camera=cam1, camera2=cam2, light=turned(proj, 2.0), volume=Volume(z_min=0.0, z_max=2000.0, r_max=3000.0))
    for name, kw in (("camera 1 and the projector", {}), ("camera 2 held (three devices)", {"uv_camera2": u2})):
        new, ref = refine_procam_rig(rig, u1, up, **kw)
        print(f"  projector of the two-camera rig, noise {noise} px, {name}: rotation error "
              f"{rotation_angle_deg(new.light.R @ proj.R.T):.4f} deg (+- {ref.rotation_std_deg:.4f}), centre "
              f"{np.linalg.norm(new.light.center - proj.center):.3f} mm ({ref.method})")


def real(data: Path) -> None:
    from ringscan.tools.cli import main

    caps = [str(data / f"capture_{i}") for i in (1, 2, 3)]
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        quiet = contextlib.redirect_stdout(io.StringIO())
        with quiet:
            assert main(["import", *caps, "--rig", str(data / "calibration_result.xml"), "--projector", "1024x768",
                         "--out", str(tmp / "scan"), "-q"]) == 0
            assert main(["calibrate", "procam", *caps, "--square", "75", "--projector", "1024x768",
                         "--out", str(tmp / "mt.json"), "-q", "--force"]) == 0
        scan = load_scan(tmp / "scan")
        pairs = [decoded_pairs(scan, v, max_pairs=70_000) for v in scan.views]
        uv = np.concatenate([p[0] for p in pairs])
        pr = np.concatenate([p[1] for p in pairs])
        print(f"real captures ({data}), {len(uv)} decoded pixels of {len(scan.views)} captures")
        rigs = (("published calibration_result.xml", scan.rig), ("fresh calibrate procam", load_rig(tmp / "mt.json")))
        for name, rig in rigs:
            ref = refine_extrinsics(rig.camera, rig.light, uv, pr)
            print(f"  {name}: epipolar median {ref.epipolar_before.median_px:.3f} -> "
                  f"{ref.epipolar_after.median_px:.3f} px, p95 {ref.epipolar_before.p95_px:.3f} -> "
                  f"{ref.epipolar_after.p95_px:.3f} px; reprojection "
                  f"median {ref.reprojection_before.median_px:.3f} -> {ref.reprojection_after.median_px:.3f} px; "
                  f"pose changed {ref.rotation_change_deg:.3f} deg (start: {ref.start}); problems: "
                  f"{ref.problems or 'none'}")


def virtual_scan(seeds=(0, 1, 2, 3), *, ring_curvature: bool = True) -> None:
    from tests.support.two_camera_scan import simulate_two_camera_scan, two_camera_rig

    from ringscan.pipeline.calibrate.rig_refine import refine_stereo_rig
    from ringscan.pipeline.formats.ply import read_ply
    from ringscan.pipeline.formats.rig import default_rig
    from ringscan.pipeline.reconstruct.settings import ReconstructSettings
    from ringscan.pipeline.reconstruct.stereo import match_view

    rig = replace(two_camera_rig(), light=default_rig(light_model="perspective").light)
    c1, c2, li = rig.camera, rig.camera2, rig.light
    Rt, tt = relative_pose(c1, c2)
    bad = replace(rig, camera2=turned(c2, 2.0))
    settings = ReconstructSettings()
    settings = replace(settings, sample=replace(settings.sample, ring_curvature=ring_curvature))
    summary, fits = [], []
    for seed in seeds:
        with tempfile.TemporaryDirectory() as tmp:
            scan = simulate_two_camera_scan(Path(tmp) / "scan", rig=rig, seed=seed)
            m = match_view(scan, scan.views[0], device="cpu", settings=settings)
            ply = read_ply(Path(tmp) / "scan" / "truth" / "object.ply")
        V = np.stack([ply["x"], ply["y"], ply["z"]], 1)
        cen = V.mean(0)
        rad = float(np.linalg.norm(V - cen, axis=1).mean())
        n1 = cv2.undistortPoints(m.uv1.reshape(-1, 1, 2), c1.K, c1.dist).reshape(-1, 2)
        n2 = cv2.undistortPoints(m.uv2.reshape(-1, 1, 2), c2.K, c2.dist).reshape(-1, 2)

        def points(R, t, n1=n1, n2=n2):
            return (triangulate_pair(R, t, n1, n2) - c1.t) @ c1.R

        def err3(X, cen=cen, rad=rad):
            return float(np.median(np.minimum(np.abs(np.linalg.norm(X - cen, axis=1) - rad), np.abs(X[:, 2]))))

        def projector(R, t, weighted=True, m=m):
            """projector-from-scan's fit: each pair weighted by its predicted uncertainty (the default) or not."""
            X = points(R, t)
            c2r = replace(c2, R=R @ c1.R, t=R @ c1.t + t)
            cov = triangulation_covariance(c1, c2r, X, m.sigma1, m.sigma2) if weighted else None
            return fit_projector(X, m.proj, size=(li.width, li.height), point_cov=cov,
                                 pixel_sigma=m.sigma_proj if weighted else None)

        _, two = refine_stereo_rig(bad, m.uv1, m.uv2)
        _, three = refine_stereo_rig(bad, m.uv1, m.uv2, sigma1=m.sigma1, sigma2=m.sigma2, uv_light=m.proj,
                                     sigma_light=m.sigma_proj)
        _, true = refine_stereo_rig(rig, m.uv1, m.uv2)
        e_true = err3(points(Rt, tt))
        if seed == seeds[0]:
            print(f"virtual two-camera scan (match_view), rendering seed {seed}: {len(m)} matches")
            for name, R, t, epi in (("turned 2 deg", two.R0, two.t0, two.epipolar_before),
                                    ("two-view", two.R, two.t, two.epipolar_after),
                                    ("three devices", three.R, three.t, three.epipolar_after),
                                    ("true rig", Rt, tt, true.epipolar_before)):
                de, dt = pose_error(R, t, Rt, tt)
                print(f"    {name:13s} epipolar median {epi.median_px:7.3f} p95 {epi.p95_px:7.3f} px | pose error "
                      f"{de:7.4f} deg {dt:7.3f} mm | 3D median error {err3(points(R, t)):8.4f} mm")
            for name, ref in (("two-view", two), ("three devices", three)):
                print(f"    {name} pose's own std: rotation {ref.rotation_std_deg:.4f} deg, direction "
                      f"{ref.direction_std_deg:.4f} deg; problems: {ref.problems or 'none'}")
            for name, R, t in (("true rig", Rt, tt), ("refined rig, three devices", three.R, three.t)):
                fit = projector(R, t)
                K, Kt = fit.light.K, li.K
                print(f"  projector-from-scan ({name}): RMS {fit.rms_px:.3f} px; fx "
                      f"{100 * (K[0, 0] / Kt[0, 0] - 1):+.3f} %, fy {100 * (K[1, 1] / Kt[1, 1] - 1):+.3f} %, "
                      f"cx {K[0, 2] - Kt[0, 2]:+.2f} px, cy {K[1, 2] - Kt[1, 2]:+.2f} px; pose "
                      f"{rotation_angle_deg(fit.light.R @ li.R.T):.4f} deg, "
                      f"{np.linalg.norm(fit.light.center - li.center):.3f} mm; std fx {fit.std['fx']:.2f} px, "
                      f"rotation {fit.std['rotation_deg']:.4f} deg; problems: {fit.problems or 'none'}")
        row = [seed, len(m), two.epipolar_after.median_px, three.epipolar_after.median_px,
               true.epipolar_before.median_px, pose_error(two.R, two.t, Rt, tt)[0],
               pose_error(three.R, three.t, Rt, tt)[0], err3(points(two.R, two.t)) / e_true,
               err3(points(three.R, three.t)) / e_true, e_true]
        summary.append(row)
        for weighted in (True, False):
            fit = projector(Rt, tt, weighted)
            K, Kt = fit.light.K, li.K
            fits.append((seed, "weighted" if weighted else "unweighted", 100 * (K[0, 0] / Kt[0, 0] - 1),
                         100 * (K[1, 2] - Kt[1, 2]) / li.height, rotation_angle_deg(fit.light.R @ li.R.T),
                         float(np.linalg.norm(fit.light.center - li.center)), fit.std["position"],
                         ", ".join(nm for nm in ("k1", "k2", "p1", "p2", "k3") if nm not in fit.fixed)))
    print("  refine from camera 2 turned 2 deg, per rendering seed (3D error as a ratio to the true rig's):")
    print("  | seed | matches | epipolar median two-view / three devices / true px | rotation error two-view / "
          "three devices deg | 3D error two-view / three devices | true rig's 3D error mm |")
    for r in summary:
        print(f"  | {r[0]} | {r[1]} | {r[2]:.3f} / {r[3]:.3f} / {r[4]:.3f} | {r[5]:.4f} / {r[6]:.4f} | "
              f"{r[7]:.2f}x / {r[8]:.2f}x | {r[9]:.4f} |")
    print("  projector-from-scan from the true rig, per rendering seed (auto distortion terms):")
    print("  | seed | weights | fx error | cy error (of the image) | pose error | own std of the position | fitted |")
    for r in fits:
        print(f"  | {r[0]} | {r[1]} | {r[2]:+.3f} % | {r[3]:+.3f} % | {r[4]:.4f} deg, {r[5]:.3f} mm | {r[6]:.3f} mm "
              f"| {r[7]} |")


def run() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--noise", type=float, nargs="+", default=[0.1, 0.3], help="pixel noise per coordinate")
    ap.add_argument("--points", type=int, default=200_000,
                    help="surface points drawn (a dense scan gives millions of matches)")
    ap.add_argument("--data", default=str(Path(__file__).resolve().parents[2] / "shared" / "data" / "procam"))
    ap.add_argument("--no-scan", action="store_true", help="skip the virtual two-camera scan")
    ap.add_argument("--scan-seeds", type=int, nargs="+", default=[0, 1, 2, 3],
                    help="rendering seeds of the virtual two-camera scan (one scan each)")
    ap.add_argument("--scan-only", action="store_true", help="only the virtual two-camera scan (section 3)")
    ap.add_argument("--ring-curvature", choices=("on", "off"), default="on",
                    help="decode the scan with SampleSettings.ring_curvature on (the default, as calibrate refine "
                         "and projector-from-scan do) or off (docs/reconstruction.md)")
    args = ap.parse_args()
    if args.scan_only:
        virtual_scan(tuple(args.scan_seeds), ring_curvature=args.ring_curvature == "on")
        return
    for noise in args.noise:
        synthetic(noise, args.points)
        projector_of_two_cameras(noise)
    if Path(args.data).is_dir():
        real(Path(args.data))
    else:
        print(f"real captures: {args.data} not found, skipped")
    if not args.no_scan:
        virtual_scan(tuple(args.scan_seeds), ring_curvature=args.ring_curvature == "on")


if __name__ == "__main__":
    run()
