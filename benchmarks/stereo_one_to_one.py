"""Two cameras at about one projector pixel per camera pixel (issue 34), on the virtual rig, through the
commands a user runs, against the plain way.

The rig (tests/support/one_to_one.py) is a public capture's scaled down by ``--scale``:
two cameras 40 mm apart beside a projector (full size 2048x1500 cameras, a 1920x1080 projector), a
plane 1 m away, ``--ratio`` = the cameras' focal length over the projector's (0.9: a camera pixel
covers 1.1 projector pixels). ``simulate --captures opencv-graycode`` renders OpenCV's Gray code;
``import`` (as it comes, and ``--integer``) with the stereo calibration alone (the projector
uncalibrated); ``reconstruct --rays camera-camera``. The plain way: integer codes (white - black >= 20,
pattern > inverse), camera 1's pixel matched to the mean of camera 2's pixels of the same code, both
triangulated with ``cv2.triangulatePoints``. Printed per import: points, their share of the plain
points, the RMS distance from the points' least-squares plane (every point counts) and its share of
the plain one's, and what the matching dropped. ``--misread S``: a share S of each camera's pixels has
one of its three finest column bits and one row bit read the wrong way (pattern and inverse swapped),
in the frames both ways read.

    python benchmarks/stereo_one_to_one.py [--scale 4] [--ratio 0.9] [--misread 0] [--work DIR]
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from ringscan.pipeline.calibrate.graycode import graycode_bits  # noqa: E402
from ringscan.pipeline.formats.images import read_image, write_image  # noqa: E402
from ringscan.pipeline.formats.ply import read_ply  # noqa: E402
from ringscan.pipeline.formats.rig import save_rig  # noqa: E402
from tests.support.one_to_one import one_to_one_rig, plain_camera_camera, plane_rms  # noqa: E402
from benchmarks.two_camera_rig import run  # noqa: E402  (one ringscan command, its console output)


def misread(render: Path, projector, share: float, seed: int = 1) -> None:
    """Swap pattern and inverse of one of the three finest column bits and one row bit at a share of each
    camera's pixels, in place."""
    rng = np.random.default_rng(seed)
    fs = cv2.FileStorage(str(render / "capture_0.yml"), cv2.FILE_STORAGE_READ)
    cb, rb = graycode_bits(projector)
    for c in (1, 2):
        node = fs.getNode(f"cam{c}")
        paths = [render / node.at(i).string() for i in range(node.size())]
        fr = [read_image(p) for p in paths]
        for first, bits in ((0, cb), (2 * cb, rb)):
            hit = rng.random(fr[0].shape) < share
            which = rng.integers(0, 3, fr[0].shape)
            for k in range(3):
                m = hit & (which == k)
                a, b = first + 2 * (bits - 1 - k), first + 2 * (bits - 1 - k) + 1
                pa, pb = fr[a].copy(), fr[b].copy()
                fr[a][m], fr[b][m] = pb[m], pa[m]
        for p, f in zip(paths, fr):
            write_image(p, f)
    fs.release()


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scale", type=int, default=4, help="the full-size rig divided by this (default 4: "
                                                         "512x375 cameras, a 480x270 projector)")
    ap.add_argument("--ratio", type=float, default=0.9, help="camera focal length over the projector's")
    ap.add_argument("--misread", type=float, default=0.0, help="share of pixels with a misread fine bit")
    ap.add_argument("--work", default=None, help="keep the renderings, scans and reconstructions here")
    a = ap.parse_args()
    work = Path(a.work) if a.work else Path(tempfile.mkdtemp(prefix="ringscan_one_to_one_"))
    work.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    rig = one_to_one_rig(scale=a.scale, ratio=a.ratio)
    proj = (rig.light.width, rig.light.height)
    render = work / "render"
    if not render.exists():
        save_rig(work / "rig.json", rig)
        run("simulate", "--rig", work / "rig.json", "--captures", "opencv-graycode", "--scene", "plane", "--out",
            render, "--no-progress", "-q")
        if a.misread > 0:
            misread(render, proj, a.misread)
    plain, decoded = plain_camera_camera(render / "capture_0.yml", render / "calibrationParameters.yml", proj)
    rms_plain = plane_rms(plain)
    c = rig.camera
    print(f"two {c.width}x{c.height} cameras 40 mm apart, a {proj[0]}x{proj[1]} projector, a plane 1 m away; "
          f"{1 / a.ratio:.2f} projector px per camera px; misread share {a.misread:g}")
    print("| import | points | x plain | plane RMS mm | x plain | sub-pixel share | unmatched (matching) |")
    print("|---|---|---|---|---|---|---|")
    print(f"| plain (integer codes, cv2.triangulatePoints) | {len(plain)} | 1.00 | {rms_plain:.3f} | 1.00 | - | "
          f"{decoded - len(plain)} (no pixel of its code in camera 2) |")
    for name, extra in (("as it comes", []), ("--integer", ["--integer"])):
        scan = work / f"scan_{'int' if extra else 'sub'}"
        if not scan.exists():
            run("import", render / "capture_0.yml", "--rig", render / "calibrationParameters.yml", "--projector",
                f"{proj[0]}x{proj[1]}", "--out", scan, "-q", *extra)
        rec = work / f"rec_{scan.name}"
        shutil.rmtree(rec, ignore_errors=True)
        run("reconstruct", scan, "--rays", "camera-camera", "--out", rec, "--no-progress", "-q")
        v = json.loads((rec / "report.json").read_text())["views"][0]
        ply = read_ply(rec / "capture_0.ply")
        P = np.stack([ply["x"], ply["y"], ply["z"]], 1).astype(np.float64)
        st = json.loads((scan / "scan.json").read_text())["imported"]["stats"]["capture_0"]
        um = ", ".join(f"{k} {n}" for k, n in v["stereo"]["unmatched"].items() if n) or "none"
        r = plane_rms(P)
        print(f"| {name} | {len(P)} | {len(P) / len(plain):.2f} | {r:.3f} | {r / rms_plain:.2f} | "
              f"{100 * st['subpixel_share']:.0f} % | {um} |")
    print(f"({time.perf_counter() - t0:.0f} s; {work})")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
