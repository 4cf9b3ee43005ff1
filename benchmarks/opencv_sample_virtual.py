"""OpenCV's structured-light sample, on the virtual two-camera rig: render, import, compare with the truth.

1. Renders the virtual two-camera rig with a projector (``small_stereo_rig`` of the tests: two
   320x256 cameras, camera 2 = camera 1 turned 180 degrees about the light axis, 482 mm apart; a
   128x96 projector with lens distortion; or ``--scale K``: cameras and projector K times larger)
   in OpenCV's sample layout: ``capture_0/pattern_camN_imK.png``, ``capture_0.yml``,
   ``calibrationParameters.yml`` (camera-camera), ``procam.yml`` (camera 1 - projector).
2. ``ringscan import capture_0.yml --rig calibrationParameters.yml`` (the library call).
3. Prints, per camera: pixels decoded, the share with sub-pixel positions, the decoded projector
   coordinates' error against the truth (median, 95th percentile, over the lit pixels away from
   edges), the working depth the import chose against the truth depths, and the plain
   camera-camera triangulation (integer codes, camera 2's pixels of one code averaged, OpenCV's
   ``triangulatePoints``) against camera 1's truth depth.

    python benchmarks/opencv_sample_virtual.py [--scale 1] [--scene sphere] [--out DIR]
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np

from ringscan.pipeline.calibrate.importer import import_captures, triangulate_codes

from ringscan.pipeline.calibrate.opencv_files import read_stereo_calibration
from ringscan.pipeline.formats.scan import as_camera2, read_view_frames
from ringscan.pipeline.simulate.opencv_graycode import read_graycode_truth, render_graycode_captures

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from tests.support.opencv_graycode_rig import small_stereo_rig  # noqa: E402


def scale_rig(rig, k: int):
    """``rig`` with its cameras and projector K times larger (same field of view; also used by two_camera_rig.py)."""
    if k == 1:
        return rig

    def cam(c):
        K = c.K.copy()
        K[:2] *= k
        K[0, 2], K[1, 2] = (c.width * k - 1) / 2, (c.height * k - 1) / 2
        return dataclasses.replace(c, width=c.width * k, height=c.height * k, K=K)

    li = rig.light
    Kp = li.K.copy()
    Kp[:2] *= k
    Kp[0, 2], Kp[1, 2] = (li.width * k - 1) / 2, (li.height * k - 1) / 2
    return dataclasses.replace(rig, camera=cam(rig.camera), camera2=cam(rig.camera2),
                               light=dataclasses.replace(li, width=li.width * k, height=li.height * k, K=Kp))


def scaled_rig(k: int):
    return scale_rig(small_stereo_rig(), k)


def decoded(scan, view, camera):
    s = as_camera2(scan) if camera == 2 else scan
    v = view.camera2 if camera == 2 else view
    fr = read_view_frames(s, v, ["proj_u", "proj_v"]).astype(np.float64)
    ok = (fr[0] > 0) & (fr[1] > 0)
    k = scan.patterns.scale
    return np.where(ok, fr[0] / k - 1, np.nan), np.where(ok, fr[1] / k - 1, np.nan)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scale", type=int, default=1, help="cameras and projector K times the test rig's size")
    ap.add_argument("--scene", default="sphere")
    ap.add_argument("--out", default=None, help="keep the rendering and the scan here")
    args = ap.parse_args()
    base = Path(args.out) if args.out else Path(tempfile.mkdtemp(prefix="opencv_sample_"))
    rig = scaled_rig(args.scale)
    proj = (rig.light.width, rig.light.height)
    t0 = time.perf_counter()
    render_graycode_captures(base / "render", rig=rig, scene=args.scene, size_mm=50.0, progress=False)
    t1 = time.perf_counter()
    scan, stats = import_captures([base / "render" / "capture_0.yml"], out=base / "scan", projector=proj,
                                  stereo=read_stereo_calibration(base / "render" / "calibrationParameters.yml"))
    t2 = time.perf_counter()
    print(f"virtual two-camera rig: cameras {rig.camera.width}x{rig.camera.height}, projector {proj[0]}x{proj[1]}, "
          f"baseline {np.linalg.norm(rig.camera.center - rig.camera2.center):.0f} mm; scene {args.scene} 50 mm; "
          f"render {t1 - t0:.1f} s, import {t2 - t1:.1f} s")
    view = scan.views[0]
    maps = {}
    for c in (1, 2):
        truth = read_graycode_truth(base / "render", camera=c)
        u, v = decoded(scan, view, c)
        maps[c] = (u, v)
        inner = cv2.erode((truth["lit"] & np.isfinite(truth["depth"])).astype(np.uint8),
                          np.ones((5, 5), np.uint8)).astype(bool)
        sel = inner & np.isfinite(u)
        e = np.hypot(u[sel] - truth["proj"][..., 0][sel], v[sel] - truth["proj"][..., 1][sel])
        st = stats["capture_0"] if c == 1 else stats["capture_0"]["camera2"]
        print(f"  camera {c}: {st['decoded']} pixels decoded, {100 * st['subpixel_share']:.1f} % sub-pixel; "
              f"inner lit pixels decoded {100 * sel.sum() / max(1, inner.sum()):.1f} %; projector coordinate error "
              f"median {np.median(e):.3f} px, p95 {np.percentile(e, 95):.3f} px")
    z1 = read_graycode_truth(base / "render", camera=1)["depth"]
    vol = scan.rig.volume
    print(f"  working depth (camera 1's axis): {vol.z_min:.0f}..{vol.z_max:.0f} mm (truth {np.nanmin(z1):.0f}.."
          f"{np.nanmax(z1):.0f} mm), r_max {vol.r_max:.0f} mm")
    # the plain way: integer codes, camera 2's pixels of one code averaged
    cal = read_stereo_calibration(base / "render" / "calibrationParameters.yml")
    (u1, v1), (u2, v2) = maps[1], maps[2]
    ok2 = np.isfinite(u2)
    y2, x2 = np.nonzero(ok2)
    code2 = np.round(v2[ok2]).astype(np.int64) * proj[0] + np.round(u2[ok2]).astype(np.int64)
    n = proj[0] * proj[1]
    cnt = np.bincount(code2, minlength=n)
    sx, sy = np.bincount(code2, x2, n), np.bincount(code2, y2, n)
    y1, x1 = np.nonzero(np.isfinite(u1) & np.isfinite(z1))
    code1 = np.round(v1[y1, x1]).astype(np.int64) * proj[0] + np.round(u1[y1, x1]).astype(np.int64)
    m = cnt[code1] > 0
    X = triangulate_codes(np.stack([x1[m], y1[m]], 1), np.stack([sx[code1[m]] / cnt[code1[m]],
                                                                  sy[code1[m]] / cnt[code1[m]]], 1),
                          cam_K=cal["cam1_K"], cam_dist=cal["cam1_dist"], proj_K=cal["cam2_K"],
                          proj_dist=cal["cam2_dist"], R=cal["R"], T=cal["T"])
    dz = np.abs(X[:, 2] - z1[y1[m], x1[m]])
    print(f"  plain camera-camera (integer codes): {m.sum()} points, |depth error| median {np.median(dz):.3f} mm, "
          f"p95 {np.percentile(dz, 95):.3f} mm")
    print(f"(files in {base})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
