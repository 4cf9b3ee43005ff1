"""Issue 33's figures: a real-capture-sized two-camera Gray-code scan through ringscan and through OpenCV's sample.

The capture is virtual (the issue's statue, OpenCV's structured-light sample data, is not in
../shared) but of its size: two 1920x1280 cameras and a projector (the virtual rig of
benchmarks/opencv_sample_virtual.py, ``small_stereo_rig`` of the tests, its cameras 6 times
larger and cropped to 1280 rows, its projector 6 times larger: 768x576), a sphere on a plane,
``simulate --captures opencv-graycode``; rendered once into ``--work DIR`` and reused.

Then, paired and interleaved in one run (``--rounds`` rounds, the median of each figure):

1. ringscan, two cameras (camera to camera): ``ringscan import capture_0.yml --rig
   calibrationParameters.yml --projector-rig procam.yml`` then ``reconstruct --rays camera-camera``;
2. ringscan, one camera and the calibrated projector: ``reconstruct --rays camera-projector`` of the
   same import;
3. OpenCV's own sample pipeline on the same captures (what OpenCV's ``structured_light``
   sample does): read the frames, ``stereoRectify`` + ``initUndistortRectifyMap`` + ``remap``
   (nearest, as the sample), ``cv2.structured_light.GrayCodePattern.decode`` (white threshold 5,
   black threshold 40) and ``reprojectImageTo3D``. Where the OpenCV build lacks
   ``cv2.structured_light`` (it is in opencv-contrib-python-headless, the project's dependency),
   the decode is a NumPy re-implementation of the same steps (the bits from pattern/inverse
   pairs, the shadow mask from white - black, the Gray code to binary, the disparity of a
   projector pixel's camera 1 and camera 2 pixels' mean columns), and the benchmark says so
   (``benchmarks/opencv_graycode_sample.py``: OpenCV and NumPy only);
4. the same as 1 and 3 as a user runs them, each its own process (``python -m ringscan.tools.cli
   import ...``, ``... reconstruct ...``, ``python benchmarks/opencv_graycode_sample.py ...``):
   start-up, imports and exit included, as the issue measured.

It prints per stage (report.json ``times_s``, the import's wall time; from the warm runs of 1-3 in
this process) microseconds a sample and samples a second, the ratio ringscan (import + two-camera
reconstruct) / OpenCV's sample as whole processes (4: bar ``peer_speed`` <= 1.0) and in this warm
process, and the one-camera triangulation of the decoded view on one core
(``triangulate_rings threads=1``, us a sample of the thread's CPU time; bar <= 0.5). Exits 1 when a bar is missed,
naming it.

    python benchmarks/real_capture.py [--work DIR] [--scale 1.0] [--rounds 3]

``--scale 0.5``: cameras and projector half the size (a quick check; the bars are the issue's
at scale 1).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import cv2

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from ringscan.pipeline.formats.rig import save_rig  # noqa: E402
from tests.support.opencv_graycode_rig import small_stereo_rig  # noqa: E402
from opencv_graycode_sample import DECODER, opencv_sample, read_list  # noqa: E402  (this folder's)
from two_camera_rig import run  # noqa: E402  (one ringscan command, its console output)

BASE_WIDTH, BASE_HEIGHT, BASE_SCALE = 1920, 1280, 6
"""The issue's cameras (1920x1280): the test rig's 320x256 cameras 6 times larger, cropped to 1280 rows."""
PEER_SPEED_BAR = 1.0
TRIANGULATE_US_BAR = 0.5
"""OpenCV GrayCodePattern thresholds (the sample's command-line values)."""


def capture_rig(scale: float):
    """The test's two-camera rig at the issue's size times ``scale``."""
    rig = small_stereo_rig()
    k = BASE_SCALE * scale
    w, h = int(round(BASE_WIDTH * scale)), int(round(BASE_HEIGHT * scale))

    def cam(c):
        K = c.K.copy()
        K[:2] *= k
        K[0, 2], K[1, 2] = (w - 1) / 2, (h - 1) / 2
        return dataclasses.replace(c, width=w, height=h, K=K)

    li = rig.light
    pw, ph = int(round(li.width * k)), int(round(li.height * k))
    Kp = li.K.copy()
    Kp[:2] *= k
    Kp[0, 2], Kp[1, 2] = (pw - 1) / 2, (ph - 1) / 2
    return dataclasses.replace(rig, camera=cam(rig.camera), camera2=cam(rig.camera2),
                               light=dataclasses.replace(li, width=pw, height=ph, K=Kp))


def render(work: Path, scale: float) -> Path:
    """The capture folder (rendered once: ``--work`` keeps it)."""
    out = work / f"render_{scale:g}"
    if (out / "truth.json").exists():
        return out
    rig = capture_rig(scale)
    save_rig(work / f"rig_{scale:g}.json", rig)
    t = time.perf_counter()
    run("simulate", "--rig", work / f"rig_{scale:g}.json", "--captures", "opencv-graycode", "--scene", "sphere",
        "--size-mm", "50", "--out", out, "--no-progress", "-q")
    print(f"rendered {out} in {time.perf_counter() - t:.0f} s")
    return out


def ringscan_import(src: Path, out: Path, projector: tuple[int, int]) -> float:
    shutil.rmtree(out, ignore_errors=True)
    t = time.perf_counter()
    run("import", src / "capture_0.yml", "--rig", src / "calibrationParameters.yml", "--projector-rig",
        src / "procam.yml", "--projector", f"{projector[0]}x{projector[1]}", "--out", out, "-q")
    return time.perf_counter() - t


def ringscan_reconstruct(scan: Path, out: Path, rays: str) -> tuple[float, dict]:
    shutil.rmtree(out, ignore_errors=True)
    t = time.perf_counter()
    run("reconstruct", scan, "--rays", rays, "--out", out, "--no-progress", "-q")
    wall = time.perf_counter() - t
    rep = json.loads((out / "report.json").read_text())
    view = rep["views"][0] if isinstance(rep.get("views"), list) else next(iter(rep["views"].values()))
    return wall, view


def triangulate_one_core(scan_dir: Path, repeats: int = 3) -> tuple[float, float, int]:
    """The one-camera triangulation of the imported view's decoded samples on one thread (``triangulate_rings
    threads=1``: its kernels run on the calling thread): (us a sample of that thread's CPU time, us a sample of
    wall time, samples), the least of ``repeats``. The CPU time is the one-core figure on a shared machine
    (the wall time counts the other processes' turns on the core too)."""
    from ringscan.kernels import init_warp
    from ringscan.kernels.triangulation import triangulate_rings
    from ringscan.pipeline.formats.scan import load_scan
    from ringscan.pipeline.geometry import camera_model_for, light_model_for
    from ringscan.pipeline.reconstruct.settings import ReconstructSettings
    from ringscan.pipeline.reconstruct.stereo import decode_view

    init_warp()
    scan = load_scan(scan_dir)
    st = ReconstructSettings()
    samples, _, _ = decode_view(scan, scan.views[0], settings=st, device="cpu", threads=1)
    rig, vol = scan.rig, scan.rig.volume
    cpu, wall = float("inf"), float("inf")
    for i in range(repeats + 1):  # the first compiles / loads the kernels
        t, c = time.perf_counter(), time.thread_time()
        triangulate_rings(samples.uv, samples.rho, samples.sector, samples.confidence, camera=camera_model_for(rig),
                          light=light_model_for(rig), volume=(vol.z_min, vol.z_max, vol.r_max),
                          center=scan.patterns.center, sector_bits=scan.patterns.sector_bits, phi=samples.phi,
                          sigma_rho=samples.sigma_rho, sigma_tan=samples.sigma_tan, settings=st.triangulate,
                          threads=1)
        if i:
            cpu, wall = min(cpu, time.thread_time() - c), min(wall, time.perf_counter() - t)
    n = max(1, len(samples))
    return 1e6 * cpu / n, 1e6 * wall / n, len(samples)


def process_seconds(*cmd) -> float:
    """Wall seconds of one command run as its own process (start-up, imports and exit included), which must
    succeed."""
    t = time.perf_counter()
    done = subprocess.run([str(c) for c in cmd], capture_output=True, text=True)
    wall = time.perf_counter() - t
    if done.returncode != 0:
        raise SystemExit(f"{' '.join(map(str, cmd))} failed ({done.returncode}):\n{done.stdout}{done.stderr}")
    return wall


def processes(src: Path, scan: Path, rec: Path, proj: tuple[int, int]) -> tuple[float, float, float]:
    """(ringscan import, ringscan reconstruct --rays camera-camera, OpenCV's sample): each its own process, as a
    user runs them (the issue's figure: whole processes)."""
    shutil.rmtree(scan, ignore_errors=True)
    shutil.rmtree(rec, ignore_errors=True)
    cli = [sys.executable, "-m", "ringscan.tools.cli"]
    t_imp = process_seconds(*cli, "import", src / "capture_0.yml", "--rig", src / "calibrationParameters.yml",
                            "--projector-rig", src / "procam.yml", "--projector", f"{proj[0]}x{proj[1]}", "--out",
                            scan, "-q")
    t_rec = process_seconds(*cli, "reconstruct", scan, "--rays", "camera-camera", "--out", rec, "--no-progress",
                            "-q")
    t_cv = process_seconds(sys.executable, Path(__file__).with_name("opencv_graycode_sample.py"), src,
                           "--projector", f"{proj[0]}x{proj[1]}")
    return t_imp, t_rec, t_cv


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--work", default=None, help="keep the rendering (and the runs' outputs) here; reused")
    ap.add_argument("--scale", type=float, default=1.0, help="cameras and projector this times the issue's size")
    ap.add_argument("--rounds", type=int, default=3, help="interleaved rounds (the median is printed)")
    args = ap.parse_args()
    work = Path(args.work) if args.work else Path(tempfile.mkdtemp(prefix="real_capture_"))
    work.mkdir(parents=True, exist_ok=True)
    src = render(work, args.scale)
    truth = json.loads((src / "truth.json").read_text())
    proj = tuple(truth["projector"])
    cw, ch = truth["camera"]
    print(f"capture: two {cw}x{ch} cameras, a {proj[0]}x{proj[1]} projector, {len(read_list(src)[1])} frames a "
          f"camera ({src})")
    print(f"OpenCV {cv2.__version__}; decode: {DECODER}")
    scan = work / f"scan_{args.scale:g}"
    rec = {r: work / f"rec_{r}_{args.scale:g}" for r in ("camera-camera", "camera-projector")}
    # a warm-up of each (kernel compile and load, file caches), not counted
    ringscan_import(src, scan, proj)
    for r, out in rec.items():
        ringscan_reconstruct(scan, out, r)
    opencv_sample(src, proj)
    rows = {"import": [], "two": [], "one": [], "opencv": [], "ratio": [], "p_import": [], "p_two": [],
            "p_opencv": [], "p_ratio": []}
    stage = {"two": {}, "one": {}, "opencv": {}}
    views = {}
    for i in range(args.rounds):
        t_imp = ringscan_import(src, scan, proj)
        t_two, v_two = ringscan_reconstruct(scan, rec["camera-camera"], "camera-camera")
        cv_stage, _ = opencv_sample(src, proj)
        t_one, v_one = ringscan_reconstruct(scan, rec["camera-projector"], "camera-projector")
        t_cv_total = sum(cv_stage.values())
        rows["import"].append(t_imp)
        rows["two"].append(t_two)
        rows["one"].append(t_one)
        rows["opencv"].append(t_cv_total)
        rows["ratio"].append((t_imp + t_two) / t_cv_total)
        for k, s in v_two["times_s"].items():
            stage["two"].setdefault(k, []).append(s)
        for k, s in v_one["times_s"].items():
            stage["one"].setdefault(k, []).append(s)
        for k, s in cv_stage.items():
            stage["opencv"].setdefault(k, []).append(s)
        views = {"two": v_two, "one": v_one}
        p_imp, p_two, p_cv = processes(src, work / f"scan_process_{args.scale:g}",
                                       work / f"rec_process_{args.scale:g}", proj)
        for k, v in (("p_import", p_imp), ("p_two", p_two), ("p_opencv", p_cv), ("p_ratio", (p_imp + p_two) / p_cv)):
            rows[k].append(v)
        print(f"  round {i + 1}: in this process: import {t_imp:.2f} s, reconstruct camera-camera {t_two:.2f} s, "
              f"camera-projector {t_one:.2f} s; OpenCV {t_cv_total:.2f} s; ratio {rows['ratio'][-1]:.2f}. As "
              f"processes: import {p_imp:.2f} s, reconstruct camera-camera {p_two:.2f} s, OpenCV's sample "
              f"{p_cv:.2f} s; ratio {rows['p_ratio'][-1]:.2f}")
    _, cv_pixels = opencv_sample(src, proj)
    med = {k: statistics.median(v) for k, v in rows.items()}
    n_two = views["two"].get("samples") or views["two"].get("pixels_decoded")
    n_one = views["one"].get("samples") or views["one"].get("pixels_decoded")
    print(f"\nmedian of {args.rounds} rounds; samples: camera 1 {n_one} decoded pixels; OpenCV: {cv_pixels} pixels "
          "with a disparity")
    print("| run | stage | s | us a sample | samples/s |")
    print("|---|---|---|---|---|")

    def line(run_name, st, s, n):
        print(f"| {run_name} | {st} | {s:.3f} | {1e6 * s / n:.3f} | {n / s:.3g} |")

    line("ringscan", "import (both cameras, wall)", med["import"], n_two)
    for k, v in stage["two"].items():
        line("two cameras", k, statistics.median(v), n_two)
    line("two cameras", "reconstruct (wall)", med["two"], n_two)
    for k, v in stage["one"].items():
        line("camera + projector", k, statistics.median(v), n_one)
    line("camera + projector", "reconstruct (wall)", med["one"], n_one)
    for k, v in stage["opencv"].items():
        line("OpenCV sample", k, statistics.median(v), n_two)
    line("OpenCV sample", "all", med["opencv"], n_two)
    print(f"points: two cameras {views['two']['points']}, camera + projector {views['one']['points']}")
    tri_us, tri_wall, tri_n = triangulate_one_core(scan)
    peer = med["p_ratio"]
    print(f"\nas processes (start-up, imports and exit included): ringscan import {med['p_import']:.2f} s + "
          f"reconstruct camera-camera {med['p_two']:.2f} s, OpenCV's sample {med['p_opencv']:.2f} s")
    print(f"peer_speed (ringscan import + camera-camera reconstruct / OpenCV's sample, whole processes, paired): "
          f"{peer:.2f} (rounds: {', '.join(f'{r:.2f}' for r in rows['p_ratio'])}; bar <= {PEER_SPEED_BAR}); in "
          f"one warm process (the stage table): {med['ratio']:.2f} (rounds: "
          f"{', '.join(f'{r:.2f}' for r in rows['ratio'])})")
    print(f"triangulation us a sample on one core (triangulate_rings threads=1, {tri_n} samples of the imported "
          f"view; the thread's CPU time): {tri_us:.3f} (bar <= {TRIANGULATE_US_BAR}; wall {tri_wall:.3f})")
    missed = []
    if args.scale == 1.0:
        if peer > PEER_SPEED_BAR:
            missed.append(f"peer_speed {peer:.2f} > {PEER_SPEED_BAR}")
        if tri_us > TRIANGULATE_US_BAR:
            missed.append(f"triangulation {tri_us:.3f} us a sample > {TRIANGULATE_US_BAR}")
    else:
        print("(scale != 1: the bars are the issue's at its size; not checked)")
    for m in missed:
        print(f"MISSED: {m}")
    return 1 if missed else 0


if __name__ == "__main__":
    sys.exit(main())
