"""A far panel under OpenCV's Gray code, whose finest bits barely modulate: the decode's bit clearance against
trusting every bit, on the virtual rig (issue 32 item 5).

The case the issue met on real captures: one camera, a 512x384 projector, a white panel about 1 m away, the
finest column and row bits carrying 5-8 % of a pixel's white - black; trusting them, the depth zigzags along the
epipolar line and the predicted sigma does not see it. Here the virtual rig renders it with its truth (the
panel is the plane z = 0): a 1280x1024 camera 1 m from the panel, 250 mm beside the projector (written to
``WORK/rig.json``), the projector's blur setting how much the finest stripes keep. Conditions:

- ``sharp``: the simulator's default blur (0.7 projector px): every bit clear (the control);
- ``far``: blur 1.45 px: the finest bit keeps ~6 % of white - black (the issue's 5-8 %), the next ~45 %;
- ``far-dark``: blur 2.0 px, albedo 0.25 under ambient light 0.3 (white - black ~44 levels): the finest bit
  ~3 %, the next ~25 %.

Each is rendered (``ringscan simulate --captures opencv-graycode``, printed), imported twice: as ``ringscan
import`` does (a bit that does not stand clear of the noise gives way to the coarser ones:
``graycode.bit_clearance``) and trusting every bit (the decode before it: its thresholds set to 0), and each
import reconstructed with the default constraint (both projector coordinates) and with ``rings``. Printed per
row: points and their share of the lit panel pixels, the error along the camera ray against the plane (median,
p95), the RMS distance from the plane, the local roughness (|z - the mean of its two neighbours along the camera
row|, mm: a misread bit's zigzag), the median predicted sigma, median |e|/sigma (a Gaussian: 0.67) and the share
beyond 3 sigma (a Gaussian: 0.3 %).

    python benchmarks/far_panel.py --work DIR [--only far far-dark] [--reuse]

About 1.5 minutes on two cores. Figures from ringscan's own renderer share its geometry (a perfectly known rig,
a Gaussian blur): they show what the decode does with weak bits, not a calibration.
"""

from __future__ import annotations

import argparse
import json
import shlex
import shutil
import subprocess
import sys
import time
from pathlib import Path

import cv2
import numpy as np

import ringscan.pipeline.calibrate.graycode as gc
from ringscan.kernels.triangulation import TriangulateSettings
from ringscan.pipeline.calibrate.importer import import_captures
from ringscan.pipeline.formats.ply import read_ply
from ringscan.pipeline.formats.rig import load_rig
from ringscan.pipeline.formats.scan import load_scan
from ringscan.pipeline.reconstruct.scan import reconstruct_scan
from ringscan.pipeline.reconstruct.settings import ReconstructSettings

PROJECTOR = (512, 384)
CONDITIONS = {  # name: simulate's rendering options
    "sharp": [],
    "far": ["--defocus", "1.45"],
    "far-dark": ["--defocus", "2.0", "--albedo", "0.25", "--ambient", "0.3"],
}
GAUSS_MEDIAN_RATIO = 0.6745


def _look_at(center, target, up=(0.0, 1.0, 0.0)) -> tuple[list, list]:
    """World-to-camera R, t of a camera at ``center`` looking at ``target``."""
    c = np.asarray(center, float)
    f = np.asarray(target, float) - c
    f /= np.linalg.norm(f)
    x = np.cross(f, up)
    x /= np.linalg.norm(x)
    R = np.stack([x, np.cross(f, x), f])
    return R.tolist(), (-R @ c).tolist()


def far_rig() -> dict:
    """The rig: a 1280x1024 camera (f 2600 px, ~0.4 mm a pixel at the panel) 1 m above the plane z = 0 and 250 mm
    beside a 512x384 projector (f 1640 px: ~1.5 camera px a projector px there), both aimed at the origin."""
    Rc, tc = _look_at((-250.0, 0.0, 1000.0), (0.0, 0.0, 0.0))
    Rp, tp = _look_at((0.0, 0.0, 1000.0), (0.0, 0.0, 0.0))
    return {"format": "ringscan.rig/1", "units": "mm",
            "camera": {"width": 1280, "height": 1024, "K": [[2600.0, 0, 639.5], [0, 2600.0, 511.5], [0, 0, 1]],
                       "dist": [0.02, -0.05, 0, 0, 0], "R": Rc, "t": tc, "response": {"gamma": 1.0}},
            "light": {"model": "perspective", "width": PROJECTOR[0], "height": PROJECTOR[1],
                      "K": [[1640.0, 0, 255.5], [0, 1640.0, 191.5], [0, 0, 1]], "dist": [0, 0, 0, 0, 0],
                      "R": Rp, "t": tp},
            "volume": {"z_min": -20.0, "z_max": 200.0, "r_max": 400.0}}


def run(cmd: list[str], work: Path) -> None:
    """Run ``cmd``, printed first with ``work`` written as WORK (its own output kept for a failure)."""
    print("$ " + " ".join(shlex.quote(c) for c in cmd).replace(str(work), "WORK").replace(sys.executable, "python"),
          flush=True)
    done = subprocess.run(cmd, capture_output=True, text=True)
    if done.returncode != 0:
        sys.stderr.write(done.stdout + done.stderr)
        raise SystemExit(f"far_panel: the command above failed (exit status {done.returncode})")


def modulation(capture: Path, bits: int) -> list[float]:
    """Median |pattern - inverse| / (white - black) of the finest three column bits over the lit pixels
    (white - black > 20 levels), finest first."""
    frames = sorted(capture.glob("graycode_*.png"))
    read = lambda k: cv2.imread(str(frames[k]), cv2.IMREAD_UNCHANGED).astype(np.float32)  # noqa: E731
    white, black = read(len(frames) - 2), read(len(frames) - 1)
    con = white - black
    lit = con > 20
    return [float(np.median(np.abs(read(2 * b) - read(2 * b + 1))[lit] / con[lit])) for b in (bits - 1, bits - 2,
                                                                                               bits - 3)]


def panel_figures(P: np.ndarray, sigma: np.ndarray, uv: np.ndarray, center: np.ndarray, lit: np.ndarray) -> dict:
    """Errors of points ``P`` ((n, 3) world mm) on the panel z = 0 seen from ``center``: e along each camera ray
    (|P - C| less the ray's distance to the plane), the RMS of z, the local roughness on the camera grid (``uv``
    (n, 2) pixel centres; ``lit`` (H, W) bool the lit panel pixels, of which ``of_lit`` is the share with a point)
    and the sigmas' honesty."""
    d = P - center
    length = np.linalg.norm(d, axis=1)
    e = length - (-center[2]) * length / d[:, 2]  # the ray C + t d / |d| meets z = 0 at t = -C_z |d| / d_z
    z = np.full(lit.shape, np.nan)
    z[np.rint(uv[:, 1]).astype(int), np.rint(uv[:, 0]).astype(int)] = P[:, 2]
    rough = np.abs(z[:, 1:-1] - 0.5 * (z[:, :-2] + z[:, 2:]))
    rough = rough[np.isfinite(rough)]
    r = np.abs(e) / sigma
    lit_px = lit[np.rint(uv[:, 1]).astype(int), np.rint(uv[:, 0]).astype(int)]
    return {"points": len(P), "of_lit": float(lit_px.sum() / max(1, lit.sum())), "median": float(np.median(np.abs(e))), "p95": float(np.percentile(np.abs(e), 95)),
            "rms_plane": float(np.sqrt(np.mean(P[:, 2] ** 2))),
            "rough_median": float(np.median(rough)) if rough.size else float("nan"),
            "rough_p95": float(np.percentile(rough, 95)) if rough.size else float("nan"),
            "sigma": float(np.median(sigma)), "ratio": float(np.median(r)), "beyond_3": float(np.mean(r > 3))}


def imported(render: Path, out: Path, every_bit: bool, reuse: bool) -> Path:
    if not (reuse and (out / "scan.json").is_file()):
        shutil.rmtree(out, ignore_errors=True)
        saved = gc.CLEAR_NOISE_SIGMAS, gc.CLEAR_CONTRAST_FRACTION
        if every_bit:
            gc.CLEAR_NOISE_SIGMAS = gc.CLEAR_CONTRAST_FRACTION = 0.0
        try:
            import_captures([render / "capture_0"], out=out, rig=load_rig(render / "rig.json"), projector=PROJECTOR)
        finally:
            gc.CLEAR_NOISE_SIGMAS, gc.CLEAR_CONTRAST_FRACTION = saved
    return out


def reconstructed(scan_dir: Path, out: Path, constraint: str, lit: np.ndarray) -> dict:
    shutil.rmtree(out, ignore_errors=True)
    scan = load_scan(scan_dir)
    reconstruct_scan(scan, out, settings=ReconstructSettings(triangulate=TriangulateSettings(constraint=constraint)),
                     progress=False)
    p = read_ply(out / f"{scan.views[0].name}.ply")
    cam = scan.rig.camera
    center = -np.asarray(cam.R, np.float64).T @ np.asarray(cam.t, np.float64)
    P = np.stack([p["x"], p["y"], p["z"]], 1).astype(np.float64)
    uv = np.stack([p["u"], p["v"]], 1)
    return panel_figures(P, p["sigma"].astype(np.float64), uv, center, lit)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--work", type=Path, required=True, help="folder for the renders, imports and reconstructions")
    ap.add_argument("--only", nargs="+", choices=list(CONDITIONS), default=list(CONDITIONS))
    ap.add_argument("--reuse", action="store_true", help="reuse the renders and imports already in WORK")
    a = ap.parse_args(argv)
    a.work.mkdir(parents=True, exist_ok=True)
    rig_path = a.work / "rig.json"
    rig_path.write_text(json.dumps(far_rig(), indent=1))
    t0 = time.perf_counter()
    rows = []
    for name in a.only:
        render = a.work / name
        if not (a.reuse and (render / "capture_0").is_dir()):
            shutil.rmtree(render, ignore_errors=True)
            run([sys.executable, "-m", "ringscan.tools.cli", "simulate", "--rig", str(rig_path), "--captures",
                 "opencv-graycode", "--scene", "plane", *CONDITIONS[name], "--out", str(render), "-q"], a.work)
        truth = json.loads((render / "truth.json").read_text())
        lit = cv2.imread(str(render / "truth" / "capture_0_lit.png"), cv2.IMREAD_UNCHANGED) > 0
        mod = modulation(render / "capture_0", int(np.ceil(np.log2(PROJECTOR[0]))))
        print(f"{name}: {' '.join(CONDITIONS[name]) or 'the defaults'} (blur {truth['settings']['defocus_px']} px); "
              f"finest column bits' median |pattern - inverse| / (white - black): "
              + ", ".join(f"{100 * m:.1f} %" for m in mod) + f"; {int(lit.sum())} lit panel pixels", flush=True)
        for how, every_bit in (("bits that stand clear", False), ("every bit trusted", True)):
            scan_dir = imported(render, a.work / f"{name}_{'every_bit' if every_bit else 'clear'}", every_bit,
                                a.reuse)
            for constraint in ("auto", "rings"):
                f = reconstructed(scan_dir, a.work / f"{scan_dir.name}_{constraint}", constraint, lit)
                rows.append((name, how, "default" if constraint == "auto" else constraint, f))
    print()
    print("| condition | import | constraint | points | of lit | median mm | p95 mm | RMS from the plane mm | "
          "roughness median / p95 mm | sigma mm | median abs(e)/sigma | beyond 3 sigma |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|")
    for name, how, constraint, f in rows:
        print(f"| {name} | {how} | {constraint} | {f['points']} | {100 * f['of_lit']:.1f} % | {f['median']:.3f} | "
              f"{f['p95']:.3f} | {f['rms_plane']:.3f} | {f['rough_median']:.3f} / {f['rough_p95']:.3f} | "
              f"{f['sigma']:.3f} | {f['ratio']:.2f} | {100 * f['beyond_3']:.1f} % |")
    print(f"({time.perf_counter() - t0:.0f} s; WORK = {a.work})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
