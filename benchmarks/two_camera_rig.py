"""Issue 21's figures for a two-camera rig, through the commands a user runs, on the virtual rig.

Every step is a ``ringscan`` command (``tools.cli.main``), on virtual-rig renderings with
ground truth (virtual-rig figures, not real data):

1. Gray code as OpenCV writes it: ``simulate --captures opencv-graycode`` of a two-camera
   rig with a projector (the test rig of tests/pipeline/simulate/test_opencv_graycode.py:
   two 320x256 cameras 482 mm apart, camera 2 = camera 1 turned 180 degrees about the light
   axis, a 128x96 projector; ``--scale K``: K times larger), a 50 mm sphere; ``import``
   with the stereo file and the projector's file (``--projector-rig``); ``reconstruct
   --rays camera-projector | camera-camera | all``; then ``calibrate refine`` of the imported
   rig with camera 2 turned by 2 degrees (three devices, and ``--two-view``).
2. ringscan's gray-rings + angle code: ``simulate`` of the two-camera rig of
   tests/support/two_camera_scan.py (two 320x256 cameras 70 degrees apart about
   the light axis, the default rig's 1024x768 perspective projector), an 80 mm sphere;
   ``reconstruct --rays ...``.
   Figures: 1. the median distance (mm) of the points from the truth (the sphere's mesh or
   the reference plane, whichever is nearer) and the coverage (the share of camera 1's lit
   truth pixels that got a point: the Gray code decodes every pixel); 2. ``ringscan
   evaluate``'s (pipeline.evaluate.metrics): the median distance from the truth surface and
   the coverage of the lit surface inside the coded annulus (ring-edge samples are sparse
   in pixels, dense on the surface).
3. The gray-rings scan with a rig file whose camera 2 is turned by 2 degrees: ``reconstruct``
   warns (the epipolar check); ``calibrate refine`` (three devices, and ``--two-view``): the
   epipolar residual and the camera-camera error against the true rig's.
4. ``calibrate projector-from-scan`` from the true and from the refined rig: the projector's
   intrinsics (%), its pose (degrees, mm) against the truth, with each distortion choice
   (``--radial``, ``--tangential``: auto, the default, and the fixed models; ``--weights``), the fit's own
   standard deviations (with the residuals' correlation, and the bound were they independent),
   the residuals' correlation and the points' depth along the projector's axis; step 1 prints
   the same for the Gray-code scan.

    python benchmarks/two_camera_rig.py [--scale 1] [--work DIR]
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import io
import json
import math
import os
import shutil
import sys
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np
import open3d as o3d

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from ringscan.pipeline.evaluate.metrics import evaluate_recon  # noqa: E402
from ringscan.pipeline.calibrate.rig_refine import relative_pose, rotation_angle_deg  # noqa: E402
from ringscan.pipeline.formats.images import read_image  # noqa: E402
from ringscan.pipeline.formats.ply import read_ply  # noqa: E402
from ringscan.pipeline.formats.rig import UncalibratedLight, default_rig, load_rig, save_rig  # noqa: E402
from ringscan.pipeline.formats.scan import load_scan, save_scan  # noqa: E402
from ringscan.tools.cli import main as cli  # noqa: E402
from tests.support.two_camera_scan import ANGLE_PATTERNS, two_camera_rig  # noqa: E402

RAYS = ("camera-projector", "camera-camera", "all")


def run(*args) -> str:
    """One ringscan command; its console output (the command must succeed)."""
    buf = io.StringIO()
    with contextlib.redirect_stdout(buf), contextlib.redirect_stderr(buf):
        rc = cli([str(a) for a in args])
    if rc != 0:
        raise SystemExit(f"ringscan {' '.join(map(str, args))} failed ({rc}):\n{buf.getvalue()}")
    return buf.getvalue()


class Truth:
    """The truth mesh (world frame) and reference plane z = 0, and camera 1's lit pixels."""

    def __init__(self, mesh: Path, lit: Path):
        m = o3d.io.read_triangle_mesh(str(mesh))
        self.scene = o3d.t.geometry.RaycastingScene()
        self.scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(m))
        self.lit = read_image(lit) > 0

    def errors(self, rec: Path, to_world=None) -> tuple[float, float, int]:
        """(median distance mm, coverage, points) of a one-view reconstruction's PLY."""
        ply = read_ply(next(p for p in sorted(rec.glob("*.ply")) if "residual" not in p.name))
        X = np.stack([ply["x"], ply["y"], ply["z"]], 1).astype(np.float64)
        if to_world is not None:
            X = to_world(X)
        d = self.scene.compute_distance(o3d.core.Tensor(X.astype(np.float32))).numpy()
        d = np.minimum(d, np.abs(X[:, 2]))
        h, w = self.lit.shape
        u = np.clip(np.round(ply["u"]).astype(int), 0, w - 1)
        v = np.clip(np.round(ply["v"]).astype(int), 0, h - 1)
        hit = np.zeros_like(self.lit)
        hit[v, u] = True
        return float(np.median(d)), float((hit & self.lit).sum() / max(1, self.lit.sum())), int(X.shape[0])


def turned(dev, deg: float):
    rv = np.array([0.3, -0.8, 0.5])
    rv *= math.radians(deg) / np.linalg.norm(rv)
    Rd, _ = cv2.Rodrigues(rv)
    return dataclasses.replace(dev, R=Rd @ dev.R, t=Rd @ dev.t)


def graycode(work: Path, k: int) -> None:
    from opencv_sample_virtual import scaled_rig  # this folder's: one way to scale the rig

    rig = scaled_rig(k)
    save_rig(work / "gc_rig.json", rig)
    li = rig.light
    t0 = time.perf_counter()
    run("simulate", "--rig", work / "gc_rig.json", "--captures", "opencv-graycode", "--scene", "sphere",
        "--size-mm", "50", "--out", work / "gc_render", "--no-progress", "-q")
    run("import", work / "gc_render" / "capture_0.yml", "--rig", work / "gc_render" / "calibrationParameters.yml",
        "--projector-rig", work / "gc_render" / "procam.yml", "--projector", f"{li.width}x{li.height}",
        "--out", work / "gc_scan", "-q")
    truth = Truth(work / "gc_render" / "truth" / "object.ply", work / "gc_render" / "truth" / "capture_0_lit.png")
    c1 = rig.camera  # the import's world is camera 1's frame; the truth is in the virtual rig's

    def to_world(Xc):
        return (Xc - c1.t) @ c1.R

    print(f"\n1. Gray code as OpenCV writes it: two {c1.width}x{c1.height} cameras, a {li.width}x{li.height} "
          "projector, a 50 mm sphere; simulate --captures opencv-graycode -> import --projector-rig -> reconstruct")
    print("| rays | points | median error mm | coverage |")
    print("|---|---|---|---|")
    for rays in RAYS:
        run("reconstruct", work / "gc_scan", "--rays", rays, "--out", work / f"gc_rec_{rays}", "--no-progress", "-q")
        med, cov, n = truth.errors(work / f"gc_rec_{rays}", to_world)
        print(f"| {rays} | {n} | {med:.4f} | {100 * cov:.1f} % |")
    # the stereo file alone: the projector uncalibrated, camera-camera (what --rays auto does then)
    run("import", work / "gc_render" / "capture_0.yml", "--rig", work / "gc_render" / "calibrationParameters.yml",
        "--projector", f"{li.width}x{li.height}", "--out", work / "gc_scan_uncal", "-q")
    run("reconstruct", work / "gc_scan_uncal", "--out", work / "gc_rec_uncal", "--no-progress", "-q")
    med, cov, n = truth.errors(work / "gc_rec_uncal", to_world)
    print(f"| camera-camera, projector uncalibrated (import without --projector-rig) | {n} | {med:.4f} | "
          f"{100 * cov:.1f} % |")
    # the imported rig with camera 2 turned by 2 degrees, refined (dense matches of every decoded pixel)
    scan = work / "gc_scan"
    irig = load_scan(scan).rig
    Rt, tt = relative_pose(irig.camera, irig.camera2)
    save_rig(work / "gc_true.json", irig)
    save_rig(work / "gc_turned.json", dataclasses.replace(irig, camera2=turned(irig.camera2, 2.0)))
    print("refine of the imported rig with camera 2 turned by 2 deg (camera-camera error after):")
    print("| rig | epipolar median px | camera 2 rotation error | its own std | camera-camera median error mm |")
    print("|---|---|---|---|---|")
    for label, src, extra in (("true", "gc_true.json", []), ("refined (three devices)", "gc_turned.json", []),
                              ("refined (--two-view)", "gc_turned.json", ["--two-view"])):
        tag = label.split()[0] + ("2" if extra else "")
        run("calibrate", "refine", scan, "--rig", work / src, "--out", work / f"gc_ref_{tag}.json", "--report",
            work / f"gc_rep_{tag}.json", "--no-progress", "-q", "--force", *extra)
        rep = json.loads((work / f"gc_rep_{tag}.json").read_text())
        fixed = irig if label == "true" else load_rig(work / f"gc_ref_{tag}.json")  # true: the rig itself
        rec = work / f"gc_fixed_rec_{tag}"
        run("reconstruct", with_rig(scan, work / f"gc_fixed_{tag}", fixed), "--rays", "camera-camera", "--out", rec,
            "--no-progress", "-q")
        med, _, _ = truth.errors(rec, to_world)
        R, _ = relative_pose(fixed.camera, fixed.camera2)
        epi = rep["epipolar_px"]["before" if label == "true" else "after"]["median_px"]
        std = "-" if label == "true" else f"{rep['rotation_std_deg']:.4f} deg"
        print(f"| {label} | {epi:.3f} | {rotation_angle_deg(R @ Rt.T):.4f} deg | {std} | {med:.4f} |")
    # the projector fitted to the two cameras' dense points (every decoded pixel matched)
    print("projector-from-scan on this scan (the true stereo rig; against the projector the import was given, "
          f"whose lens has k1 {want_dist(irig)}):")
    projector_table(work, scan, work / "gc_true.json", irig.light, "gc")
    print(f"({time.perf_counter() - t0:.0f} s)")


CASES = (("auto, weighted (the default)", []),
         ("auto, --weights none", ["--weights", "none"]),
         ("--radial fit --tangential hold --weights none (the default before)",
          ["--radial", "fit", "--tangential", "hold", "--weights", "none"]),
         ("--radial fit --tangential fit --weights none", ["--radial", "fit", "--tangential", "fit", "--weights",
                                                           "none"]))
"""projector-from-scan's distortion choices the benchmark prints."""


def want_dist(rig) -> str:
    d = rig.light.dist
    return f"{d[0]:g}, k2 {d[1]:g}, p1 {d[2]:g}, p2 {d[3]:g}, k3 {d[4]:g}"


def projector_table(work: Path, scan: Path, rig_file: Path, want, tag: str, *, label: str = "true rig",
                    cases=CASES, header: bool = True) -> None:
    """``calibrate projector-from-scan`` with each distortion choice: its errors against the projector ``want``,
    what it fitted, its own standard deviations (with the residuals' correlation; and were they independent:
    the Cramer-Rao bound) and the points' depth along the projector's axis."""
    if header:
        print("| cameras from | distortion | fx, fy error | cx, cy error (of the image) | pose error | RMS | fitted "
              "| own std fx, pose (independent residuals) | residual correlation | depth 5-95 % |")
        print("|---|---|---|---|---|---|---|---|---|---|")
    for i, (what, extra) in enumerate(cases):
        out = work / f"{tag}_pfs{i}"
        run("calibrate", "projector-from-scan", scan, "--rig", rig_file, "--out", f"{out}_procam.json",
            "--stereo-out", f"{out}_rig3.json", "--report", f"{out}.json", "--no-progress", "-q", "--force", *extra)
        got = load_rig(f"{out}_rig3.json").light
        rep = json.loads(Path(f"{out}.json").read_text())["projector"]
        K, Kt = got.K, want.K
        sd, sn = rep["std"], rep["std_noise"]
        fitted = ", ".join(nm for nm in ("k1", "k2", "p1", "p2", "k3") if nm not in rep["fixed"]) or "none"
        z0, z1 = rep["depth_range"]
        print(f"| {label} | {what} | {100 * (K[0, 0] / Kt[0, 0] - 1):+.3f} %, {100 * (K[1, 1] / Kt[1, 1] - 1):+.3f} % "
              f"| {100 * (K[0, 2] - Kt[0, 2]) / want.width:+.3f} %, {100 * (K[1, 2] - Kt[1, 2]) / want.height:+.3f} % "
              f"| {rotation_angle_deg(got.R @ want.R.T):.4f} deg, {np.linalg.norm(got.center - want.center):.3f} mm "
              f"| {rep['rms_px']:.3f} px | {fitted} | {100 * sd['fx'] / K[0, 0]:.3f} %, {sd['rotation_deg']:.4f} deg, "
              f"{sd['position']:.3f} mm ({100 * sn['fx'] / K[0, 0]:.3f} %, {sn['rotation_deg']:.4f} deg, "
              f"{sn['position']:.3f} mm) | {rep['correlation']:.1f}x | {z0:.0f}-{z1:.0f} mm "
              f"({100 * rep['depth_ratio']:.1f} %) |")


def with_rig(src: Path, dst: Path, rig) -> Path:
    """A copy of scan ``src`` whose rig is ``rig`` (the frames hard-linked, not copied)."""
    shutil.rmtree(dst, ignore_errors=True)
    shutil.copytree(src, dst, copy_function=os.link, ignore=shutil.ignore_patterns("truth", "*.json"))
    for name in ("scan.json", "rig.json"):
        if (src / name).is_file():
            shutil.copy(src / name, dst / name)
    scan = load_scan(dst)
    save_scan(dataclasses.replace(scan, rig=rig, rig_ref=None))
    return dst


def rings(work: Path) -> None:
    rig = dataclasses.replace(two_camera_rig(), light=default_rig(light_model="perspective").light)
    save_rig(work / "rings_rig.json", rig)
    p = ANGLE_PATTERNS
    t0 = time.perf_counter()
    run("simulate", "--rig", work / "rings_rig.json", "--codec", "gray-rings", "--bits", p["bits"], "--pitch",
        p["pitch"], "--rho0", p["rho0"], "--sector-bits", p["sector_bits"], "--angle-steps", p["angle_steps"],
        "--angle-period", p["angle_period"], "--scene", "sphere", "--out", work / "rings_scan", "--no-progress", "-q")
    scan = work / "rings_scan"
    truth_scan = load_scan(scan)

    def errors(rec):
        ev = evaluate_recon(rec, truth_scan)
        return ev["all"]["median_mm"], ev["views"]["view_000"]["coverage"], ev["all"].get("points", 0)
    c1 = rig.camera
    print(f"\n2. ringscan's gray-rings + angle: two {c1.width}x{c1.height} cameras 70 deg apart, the "
          f"{rig.light.width}x{rig.light.height} projector, an 80 mm sphere; simulate -> reconstruct")
    print("| rays | points | median error mm | coverage |")
    print("|---|---|---|---|")
    err = {}
    for rays in RAYS:
        run("reconstruct", scan, "--rays", rays, "--out", work / f"rings_rec_{rays}", "--no-progress", "-q")
        med, cov, n = errors(work / f"rings_rec_{rays}")
        err[rays] = med
        print(f"| {rays} | {n} | {med:.4f} | {100 * cov:.1f} % |")
    li = rig.light
    unc = dataclasses.replace(rig, light=UncalibratedLight(width=li.width, height=li.height, gamma=li.gamma))
    run("reconstruct", with_rig(scan, work / "uncal_scan", unc), "--out", work / "rings_rec_uncal", "--no-progress",
        "-q")
    med, cov, n = errors(work / "rings_rec_uncal")
    print(f"| camera-camera, projector uncalibrated | {n} | {med:.4f} | {100 * cov:.1f} % |")
    print(f"({time.perf_counter() - t0:.0f} s)")

    # 3. a rig file whose camera 2 is turned by 2 degrees
    bad = dataclasses.replace(rig, camera2=turned(rig.camera2, 2.0))
    save_rig(work / "bad_rig.json", bad)
    out = run("reconstruct", with_rig(scan, work / "bad_scan", bad), "--rays", "camera-camera", "--out",
              work / "bad_rec", "--no-progress")
    warn = [ln.strip() for ln in out.splitlines() if "fit" in ln.lower() and ("warn" in ln.lower() or "not" in ln)]
    med_bad, _, _ = errors(work / "bad_rec")
    print("\n3. rig file with camera 2 turned by 2 deg: reconstruct --rays camera-camera says:")
    print("   " + (warn[0] if warn else "(no warning found in the output)"))
    print("| rig | epipolar median / p95 px | camera 2 pose error | camera-camera median error mm |")
    print("|---|---|---|---|")
    run("calibrate", "refine", scan, "--rig", work / "rings_rig.json", "--out", work / "true_again.json",
        "--report", work / "true_rep.json", "--no-progress", "-q")
    true_epi = json.loads((work / "true_rep.json").read_text())["epipolar_px"]["before"]
    rep_bad = None
    rows = []
    for label, extra in (("refined (three devices)", []), ("refined (--two-view)", ["--two-view"])):
        tag = "two" if extra else "three"
        run("calibrate", "refine", scan, "--rig", work / "bad_rig.json", "--out", work / f"refined_{tag}.json",
            "--report", work / f"rep_{tag}.json", "--no-progress", "-q", *extra)
        rep = json.loads((work / f"rep_{tag}.json").read_text())
        rep_bad = rep_bad or rep["epipolar_px"]["before"]
        fixed = load_rig(work / f"refined_{tag}.json")
        run("reconstruct", with_rig(scan, work / f"fixed_{tag}", fixed), "--rays", "camera-camera", "--out",
            work / f"fixed_rec_{tag}", "--no-progress", "-q")
        med, _, _ = errors(work / f"fixed_rec_{tag}")
        R, t = relative_pose(fixed.camera, fixed.camera2)
        Rt, tt = relative_pose(rig.camera, rig.camera2)
        rows.append(f"| {label} | {rep['epipolar_px']['after']['median_px']:.3f} / "
                    f"{rep['epipolar_px']['after']['p95_px']:.3f} | {rotation_angle_deg(R @ Rt.T):.4f} deg, "
                    f"{np.linalg.norm(t - tt):.3f} mm | {med:.4f} ({med / err['camera-camera']:.2f}x the true rig's) |")
    print(f"| turned 2 deg | {rep_bad['median_px']:.3f} / {rep_bad['p95_px']:.3f} | 2 deg | {med_bad:.4f} |")
    print("\n".join(rows))
    print(f"| true | {true_epi['median_px']:.3f} / {true_epi['p95_px']:.3f} | 0 | {err['camera-camera']:.4f} |")

    # 4. projector-from-scan
    print("\n4. calibrate projector-from-scan (the projector fitted to the two cameras' points; the projector has "
          "no lens distortion)")
    projector_table(work, scan, work / "rings_rig.json", li, "rings_t", label="true rig")
    projector_table(work, scan, work / "refined_three.json", li, "rings_r", label="refined rig (three devices)",
                    cases=CASES[:1], header=False)
    print(f"({time.perf_counter() - t0:.0f} s in all for 2-4)")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scale", type=int, default=1, help="the Gray-code rig's cameras and projector K times larger")
    ap.add_argument("--work", default=None, help="keep the renderings, scans and reconstructions here")
    args = ap.parse_args()
    work = Path(args.work) if args.work else Path(tempfile.mkdtemp(prefix="two_camera_rig_"))
    if (work / "gc_rig.json").is_file():  # an earlier run's folder: start afresh
        shutil.rmtree(work)
    work.mkdir(parents=True, exist_ok=True)
    print("virtual-rig figures (ground truth known), every step a ringscan command")
    graycode(work, args.scale)
    rings(work)
    print(f"(files in {work})")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
