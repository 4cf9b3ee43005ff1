"""Every ratio of projector to camera pixels a rig may have, on the virtual rig: OpenCV's Gray code imported,
and ringscan's default patterns, from a camera far finer than the projector to one far coarser.

1. ``import``: a 1280x1024 camera 1 m from a plane (the far panel's rig, ``benchmarks/far_panel.py``), the
   projector beside it with its focal length set so that a camera px spans r projector px (r = 1/15 ... 5: a
   512x384 projector up to r = 1.25, a 1920x1080 one beyond); rendered (``ringscan simulate --captures
   opencv-graycode``), imported and reconstructed. Printed: decoded pixels, the share with sub-pixel positions,
   the share whose finest bits the camera cannot resolve (``unresolved``), the decode's error against the
   truth's projector coordinates (median |du|, projector px), the points' error along the camera ray against
   the truth's depth (median, p95 mm) and median |e|/sigma and the share beyond 3 sigma.
2. ``gray-rings``: the default rig (perspective light) and patterns on the sphere, the camera's focal length x
   z (z = 0.25 ... 8: a projector px over 0.2 ... 6.7 camera px); rendered, reconstructed and evaluated
   (``evaluate_view``): points, coverage, median error, the sigmas' honesty.
3. ``two-cameras``: two 640x512 cameras either side of a 1920x1080 projector (``simulate --camera2``'s
   symmetric pair) over the sphere on its plane, the projector's focal length such that a camera px spans r
   projector px (r = 1.25, 2.5, 5); OpenCV's Gray code rendered, imported with the stereo file and the
   projector's calibration, reconstructed camera to camera and by all three rays; the points against camera
   1's truth depth: median error, median |e|/sigma, share beyond 3 sigma, and the same as the matcher predicts
   them (the matches' error model left out, ``reconstruct.stereo.match_error_model``), with the fitted model.

    python benchmarks/pixel_ratio.py --work DIR [--only import gray-rings two-cameras] [--reuse]

About 3 minutes on two cores. Figures from ringscan's own renderer (docs/calibration.md, "A projector finer
than the camera" and "A camera far finer than the projector"; docs/reconstruction.md, "Sample").
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
import time
from pathlib import Path

import cv2
import numpy as np

from ringscan.pipeline.calibrate.importer import import_captures
from ringscan.pipeline.evaluate.metrics import evaluate_view
from ringscan.pipeline.formats.patterns import parse_patterns
from ringscan.pipeline.formats.ply import read_ply
from ringscan.pipeline.formats.rig import default_rig, load_rig, rig_to_dict
from ringscan.pipeline.formats.scan import load_scan
from ringscan.pipeline.reconstruct.scan import reconstruct_scan
from ringscan.pipeline.reconstruct.view import reconstruct_view
from ringscan.pipeline.simulate.opencv_graycode import render_graycode_captures
from ringscan.pipeline.simulate.scan import simulate_scan

RATIOS = (1 / 15, 1 / 5, 0.75, 1.25, 2.5, 5.0)
"""Projector px a camera px spans in the import part."""
TWO_CAMERA_RATIOS = (1.25, 2.5, 5.0)
"""Projector px a camera px spans in the two-camera part."""
ZOOMS = (0.25, 0.35, 0.5, 1, 2, 3, 4, 8)
"""The camera's focal length over the default rig's in the gray-rings part."""
CAMERA_PX_PER_MM = 2600.0 / 1031.0
"""The import rig's camera px a mm at the plane (f 2600 px, 1031 mm away)."""


def import_rig(r: float) -> tuple[dict, tuple[int, int]]:
    """The far panel's rig with the projector's focal length such that a camera px spans ``r`` projector px."""
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from far_panel import far_rig  # (the same camera, projector position and volume)

    rig = far_rig()
    size = (512, 384) if r <= 1.25 else (1920, 1080)
    f = r * CAMERA_PX_PER_MM * 1000.0
    rig["light"].update(width=size[0], height=size[1],
                        K=[[f, 0, (size[0] - 1) / 2], [0, f, (size[1] - 1) / 2], [0, 0, 1]])
    rig["volume"] = {"z_min": -20.0, "z_max": 200.0, "r_max": 3000.0}
    return rig, size


def import_figures(render: Path, scan_dir: Path, rec: Path) -> dict:
    """The import's decode against the truth's projector coordinates, its points against the truth's depth."""
    scan = load_scan(scan_dir)
    k = scan.patterns.scale
    tu = cv2.imread(str(render / "truth" / "capture_0_proj_u.tiff"), cv2.IMREAD_UNCHANGED).astype(np.float64)
    fu = cv2.imread(str(scan_dir / "capture_0" / "proj_u.png"), cv2.IMREAD_UNCHANGED).astype(np.float64)
    ok = (fu > 0) & np.isfinite(tu)
    du = np.abs(fu[ok] / k - 1.0 - tu[ok])
    st = json.loads((scan_dir / "scan.json").read_text())["imported"]["stats"]["capture_0"]
    p = read_ply(rec / "capture_0.ply")
    cam = load_rig(render / "rig.json").camera
    P = np.stack([p["x"], p["y"], p["z"]], 1).astype(np.float64)
    Xc = P @ np.asarray(cam.R).T + np.asarray(cam.t)
    depth = cv2.imread(str(render / "truth" / "capture_0_depth.tiff"), cv2.IMREAD_UNCHANGED).astype(np.float64)
    d = depth[np.rint(p["v"]).astype(int), np.rint(p["u"]).astype(int)]
    good = np.isfinite(d) & (d > 0)
    e = (Xc[good, 2] - d[good]) * np.linalg.norm(Xc[good], axis=1) / Xc[good, 2]  # along the ray
    ratio = np.abs(e) / p["sigma"][good]
    return {"decoded": st["decoded"], "subpixel": st["subpixel_share"], "unresolved": st.get("unresolved_share", 0.0),
            "du": float(np.median(du)), "median": float(np.median(np.abs(e))), "p95": float(np.percentile(np.abs(e), 95)),
            "ratio": float(np.median(ratio)), "beyond_3": float(np.mean(ratio > 3))}


def run_import(work: Path, reuse: bool) -> None:
    print("| projector px a camera px | projector | decoded | sub-pixel | unresolved | decode median px | median mm | "
          "p95 mm | median abs(e)/sigma | beyond 3 sigma |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for r in RATIOS:
        rig, size = import_rig(r)
        tag = f"r{r:.3f}"
        render, scan_dir, rec = work / f"import_{tag}", work / f"import_{tag}_scan", work / f"import_{tag}_rec"
        if not (reuse and (render / "capture_0").is_dir()):
            shutil.rmtree(render, ignore_errors=True)
            (work / f"{tag}_rig.json").write_text(json.dumps(rig))
            render_graycode_captures(render, rig=load_rig(work / f"{tag}_rig.json"), scene="plane", progress=False)
        if not (reuse and (scan_dir / "scan.json").is_file()):
            shutil.rmtree(scan_dir, ignore_errors=True)
            import_captures([render / "capture_0"], out=scan_dir, rig=load_rig(render / "rig.json"), projector=size)
        shutil.rmtree(rec, ignore_errors=True)
        reconstruct_scan(load_scan(scan_dir), rec, progress=False)
        f = import_figures(render, scan_dir, rec)
        print(f"| {r:.3g} | {size[0]}x{size[1]} | {f['decoded']} | {100 * f['subpixel']:.0f} % | "
              f"{100 * f['unresolved']:.0f} % | {f['du']:.3f} | {f['median']:.4f} | {f['p95']:.4f} | {f['ratio']:.2f} | "
              f"{100 * f['beyond_3']:.1f} % |", flush=True)


def run_gray_rings(work: Path, reuse: bool) -> None:
    from ringscan.pipeline.geometry import projector_px_span

    print("| camera focal x | camera px a projector px | points | coverage | median mm | median abs(e)/sigma | "
          "beyond 3 sigma |")
    print("|---|---|---|---|---|---|---|")
    for z in ZOOMS:
        rig = default_rig(light_model="perspective")
        d = rig_to_dict(rig)
        d["camera"]["K"][0][0] *= z
        d["camera"]["K"][1][1] *= z
        (work / f"zoom{z}_rig.json").write_text(json.dumps(d))
        rig = load_rig(work / f"zoom{z}_rig.json")
        folder = work / f"gray_rings_zoom{z}"
        if not (reuse and (folder / "scan.json").is_file()):
            shutil.rmtree(folder, ignore_errors=True)
            simulate_scan(folder, scene="sphere", rig=rig, patterns=parse_patterns({"codec": "gray-rings", "width": 1024,
                          "height": 768, "center": [511.5, 383.5], "rho0": 8.0, "pitch": 4.0, "bits": 7,
                          "sector_bits": 9, "angle_steps": 4, "angle_period": 8.0}), progress=False)
        scan = load_scan(folder)
        cloud = reconstruct_view(scan, scan.views[0])
        if len(cloud.points) == 0:
            print(f"| {z} | {projector_px_span(rig):.2f} | 0 | 0 % | - | - | - |", flush=True)
            continue
        ev = evaluate_view(scan, scan.views[0].name, cloud.points, sigma=cloud.sigma)
        print(f"| {z} | {projector_px_span(rig):.2f} | {len(cloud.points)} | {100 * ev['coverage']:.1f} % | "
              f"{ev['median_mm']:.4f} | {ev['sigma']['median_ratio']:.2f} | {100 * ev['sigma']['beyond_3']:.1f} % |",
              flush=True)


def two_camera_rig(r: float):
    """Two 640x512 cameras (f 1300 px, a barrel lens) 1 m from the sphere's plane, 250 mm either side of a
    1920x1080 projector whose focal length makes a camera px span ``r`` projector px there (the far panel's
    camera position, ``simulate --camera2``'s mirror of it about the light axis)."""
    from ringscan.pipeline.formats.rig import parse_rig
    from ringscan.pipeline.simulate.scan import add_camera2

    rig = import_rig(1.0)[0]
    rig["camera"].update(width=640, height=512, K=[[1300.0, 0, 319.5], [0, 1300.0, 255.5], [0, 0, 1]],
                         dist=[-0.3, 0.12, 0, 0, 0])
    fp = r * 1300.0 * 1000.0 / 1031.0  # a camera px at the plane over a projector px there
    rig["light"].update(width=1920, height=1080, K=[[fp, 0, 959.5], [0, fp, 539.5], [0, 0, 1]])
    rig["volume"] = {"z_min": -20.0, "z_max": 200.0, "r_max": 400.0}
    return add_camera2(parse_rig(rig))


def two_camera_figures(render: Path, rec: Path) -> dict:
    """Camera 1's points (world = camera 1's frame after the import) against its truth depth along the ray."""
    p = read_ply(rec / "capture_0.ply")
    P = np.stack([p["x"], p["y"], p["z"]], 1).astype(np.float64)
    depth = cv2.imread(str(render / "truth" / "capture_0_depth.tiff"), cv2.IMREAD_UNCHANGED).astype(np.float64)
    d = depth[np.rint(p["v"]).astype(int), np.rint(p["u"]).astype(int)]
    good = np.isfinite(d) & (d > 0)
    e = (P[good, 2] - d[good]) * np.linalg.norm(P[good], axis=1) / P[good, 2]
    ratio = np.abs(e) / p["sigma"][good]
    return {"points": int(good.sum()), "median": float(np.median(np.abs(e))), "ratio": float(np.median(ratio)),
            "beyond_3": float(np.mean(ratio > 3))}


def run_two_cameras(work: Path, reuse: bool) -> None:
    from ringscan.pipeline.reconstruct import stereo
    from ringscan.pipeline.reconstruct.settings import ReconstructSettings, StereoSettings

    print("| projector px a camera px | rays | points | median mm | median abs(e)/sigma | beyond 3 sigma | "
          "as the matcher predicts: median abs(e)/sigma | beyond 3 sigma | fitted k | floor px |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    fit = stereo.match_error_model
    for r in TWO_CAMERA_RATIOS:
        tag = f"r{r:.3f}"
        render, scan_dir = work / f"two_{tag}", work / f"two_{tag}_scan"
        if not (reuse and (render / "capture_0").is_dir()):
            shutil.rmtree(render, ignore_errors=True)
            render_graycode_captures(render, rig=two_camera_rig(r), scene="sphere", progress=False)
        if not (reuse and (scan_dir / "scan.json").is_file()):
            shutil.rmtree(scan_dir, ignore_errors=True)
            # (as a user types it: the stereo file and the projector's own calibration)
            done = subprocess.run([sys.executable, "-m", "ringscan", "import", str(render / "capture_0.yml"), "--rig",
                                   str(render / "calibrationParameters.yml"), "--projector-rig",
                                   str(render / "procam.yml"), "--projector", "1920x1080", "--out", str(scan_dir),
                                   "-q", "--no-progress"], capture_output=True, text=True)
            if done.returncode != 0:
                sys.stderr.write(done.stdout + done.stderr)
                raise SystemExit(f"pixel_ratio: the import of {render} failed (exit status {done.returncode})")
        scan = load_scan(scan_dir)
        for rays in ("camera-camera", "all"):
            settings = ReconstructSettings(stereo=StereoSettings(rays=rays))
            out = {}
            for key, model in (("fitted", fit), ("predicted", lambda *a, **k: {})):
                stereo.match_error_model = model
                try:
                    rec = work / f"two_{tag}_{rays}_{key}"
                    shutil.rmtree(rec, ignore_errors=True)
                    rep = reconstruct_scan(scan, rec, settings=settings, progress=False)
                finally:
                    stereo.match_error_model = fit
                out[key] = (two_camera_figures(render, rec), rep["views"][0]["stereo"].get("error_model", {}))
            (f, m), (g, _) = out["fitted"], out["predicted"]
            print(f"| {r:.3g} | {rays} | {f['points']} | {f['median']:.4f} | {f['ratio']:.2f} | "
                  f"{100 * f['beyond_3']:.1f} % | {g['ratio']:.2f} | {100 * g['beyond_3']:.1f} % | "
                  f"{m.get('k', 1.0):.2f} | {m.get('floor_px', 0.0):.4f} |", flush=True)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--work", type=Path, required=True, help="folder for the renders and their reconstructions")
    parts = ["import", "gray-rings", "two-cameras"]
    ap.add_argument("--only", nargs="+", choices=parts, default=parts)
    ap.add_argument("--reuse", action="store_true", help="reuse the renders (and imports) already in WORK")
    a = ap.parse_args(argv)
    a.work.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    if "import" in a.only:
        run_import(a.work, a.reuse)
        print()
    if "gray-rings" in a.only:
        run_gray_rings(a.work, a.reuse)
        print()
    if "two-cameras" in a.only:
        run_two_cameras(a.work, a.reuse)
    print(f"({time.perf_counter() - t0:.0f} s)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
