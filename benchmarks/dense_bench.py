"""Dense-ring figures on the virtual rig (issue 3): speed, accuracy, high-density limits.

    python benchmarks/dense_bench.py speed     [--scan DIR] [--repeats N]
    python benchmarks/dense_bench.py accuracy  [--scene MESH]
    python benchmarks/dense_bench.py density   [--scene MESH] [--quick]

``speed``: the dense stages (decode, phase, smooth + compaction, triangulation)
on the Warp CPU backend (and CUDA where present) against their NumPy twins, in one
run (``ringscan.tools.bench.dense.bench_dense``).

``accuracy``: phase-rings (4 steps, pitch 8, 6 sector bits) on the default rig
with gamma 2.2 and with gamma 1.0, and gray-rings at pitch 2 px (7 bits): point
error against the truth surface, the fraction of lit object pixels that became
points, mislabelled ring samples.

``density``: gray-rings at pitch 2 px under stress, one factor at a time from the
default rig: camera pixels per band (a camera with the same field of view and
fewer, larger pixels), projector defocus, sensor noise, and 10 bits. For each:
ring samples, samples per lit object pixel, coverage, mislabelled samples (the
truth surface's ring radius at the sample is more than half a band from the
sample's ring: a wrong label or a sub-pixel position off by half a band), those
a whole band or more off (label errors), and points more than 1 mm off. The
decoder is right when these stay near 0 and the samples fall away instead.

Figures print as tables; nothing here is a test.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
SPOT = REPO.parent / "shared" / "data" / "models" / "odedstein_spot.obj"
PROJ = {"width": 1024, "height": 768, "center": [511.5, 383.5]}


def _scene(arg):
    if arg:
        return arg
    return str(SPOT) if SPOT.is_file() else "sphere"


def scaled_rig(scale: float, gamma: float = 2.2):
    """The default rig with a camera of the same field of view and 1/scale as many pixels per side."""
    from ringscan.pipeline.formats.rig import default_rig

    rig = default_rig(gamma=gamma)
    c = rig.camera
    if scale == 1.0:
        return rig
    w, h = int(round(c.width / scale)), int(round(c.height / scale))
    K = c.K.copy()
    K[0, 0], K[1, 1] = c.K[0, 0] * w / c.width, c.K[1, 1] * h / c.height
    K[0, 2], K[1, 2] = (w - 1) / 2.0, (h - 1) / 2.0
    return dataclasses.replace(rig, camera=dataclasses.replace(c, width=w, height=h, K=K))


def _lit_object_fraction(scan, view_name, uv):
    from ringscan.pipeline.evaluate.metrics import truth_points

    X, pix = truth_points(scan, view_name)
    obj = pix[X[:, 2] > 0.5]
    w, h = scan.rig.camera.width, scan.rig.camera.height
    have = np.zeros(w * h, bool)
    p = np.rint(uv).astype(np.int64)
    inside = (p[:, 0] >= 0) & (p[:, 0] < w) & (p[:, 1] >= 0) & (p[:, 1] < h)
    have[p[inside, 1] * w + p[inside, 0]] = True
    return float(have[obj].mean()) if obj.size else 0.0, int(obj.size)


def _measure(scan):
    """Reconstruct view 0 and measure it against the truth."""
    from ringscan.pipeline.evaluate.metrics import evaluate_view, truth_rho_at
    from ringscan.pipeline.reconstruct.view import reconstruct_view

    view = scan.views[0]
    t = time.perf_counter()
    cloud = reconstruct_view(scan, view, device="cpu")
    t_rec = time.perf_counter() - t
    ev, d = evaluate_view(scan, view.name, cloud.points, return_distances=True)
    out = {"points": int(len(d)), "samples": cloud.stats.get("samples"), "median_mm": ev["median_mm"],
           "p95_mm": ev["p95_mm"], "frac_over_1mm": ev["frac_over_1mm"], "coverage": ev.get("coverage"),
           "reconstruct_s": t_rec}
    spec = scan.patterns
    if spec.codec == "gray-rings":
        rt = truth_rho_at(scan, view.name, cloud.uv)
        judged = np.isfinite(rt)
        off = np.abs(rt - (spec.rho0 + spec.pitch * cloud.ring)) / spec.pitch
        wrong = judged & (off > 0.5)
        out.update(judged=int(judged.sum()), mislabelled=int(wrong.sum()),
                   off_by_a_band=int(np.sum(judged & (off >= 1.0))),
                   mislabelled_over_1mm=int(np.sum(wrong & (d > 1.0))))
        samp_per_px, n_obj = _lit_object_fraction(scan, view.name, cloud.uv)
        out["object_pixels_with_sample"] = samp_per_px
    else:
        out["lit_object_fraction"], _ = _lit_object_fraction(scan, view.name, cloud.uv)
    return out


def _simulate(folder, scene, rig, patterns, **render):
    from ringscan.pipeline.formats.patterns import parse_patterns
    from ringscan.pipeline.simulate.scan import simulate_scan
    from ringscan.pipeline.simulate.virtual_rig import RenderSettings

    return simulate_scan(folder, scene=scene, rig=rig, patterns=parse_patterns(patterns),
                         settings=RenderSettings(**render), progress=False)


def cmd_speed(args):
    from ringscan.tools.bench.dense import bench_dense

    bench_dense(scan_dir=args.scan, scene=args.scene, repeats=args.repeats)


def cmd_accuracy(args):
    from ringscan.pipeline.formats.rig import default_rig

    scene = _scene(args.scene)
    phase = {"codec": "phase-rings", **PROJ, "rho0": 8.0, "pitch": 8.0, "bits": 6, "sector_bits": 6, "steps": 4}
    gray2 = {"codec": "gray-rings", **PROJ, "rho0": 8.0, "pitch": 2.0, "bits": 7, "sector_bits": 6}
    rows = {}
    with tempfile.TemporaryDirectory(prefix="ringscan-dense-acc-") as tmp:
        for name, pat, g in (("phase-rings gamma 2.2", phase, 2.2), ("phase-rings gamma 1.0", phase, 1.0),
                             ("gray-rings pitch 2", gray2, 2.2)):
            scan = _simulate(Path(tmp) / name.replace(" ", "_"), scene, default_rig(gamma=g), pat)
            rows[name] = _measure(scan)
            print(name, json.dumps(rows[name]), flush=True)
    r22, r10 = rows["phase-rings gamma 2.2"]["median_mm"], rows["phase-rings gamma 1.0"]["median_mm"]
    print(f"median ratio gamma 2.2 / gamma 1.0: {r22 / r10:.3f}")


def cmd_density(args):
    scene = _scene(args.scene)
    base = {"codec": "gray-rings", **PROJ, "rho0": 8.0, "pitch": 2.0, "bits": 7, "sector_bits": 6}
    # camera px per band on the plane: 2 proj px * 0.15 mm / (0.1615 mm * scale)
    runs = [("baseline", 1.0, {}, base)]
    scales = (1.5, 2.0, 3.0, 4.0) if not args.quick else (2.0, 4.0)
    runs += [(f"camera 1/{s:g}", s, {}, base) for s in scales]
    runs += [(f"defocus {d:g} px", 1.0, {"defocus_px": d}, base) for d in ((1.5, 2.5, 4.0) if not args.quick else (2.5,))]
    runs += [(f"noise {n:g}", 1.0, {"noise": n}, base) for n in ((5.0, 10.0, 20.0) if not args.quick else (10.0,))]
    runs += [("10 bits", 1.0, {}, {**base, "bits": 10})]
    print(f"{'run':<16}{'cam px/band':>12}{'samples':>9}{'obj px w/ sample':>17}{'coverage':>9}{'judged':>8}"
          f"{'>0.5 band':>10}{'>=1 band':>9}{'>0.5b & >1mm':>13}{'>1mm %':>8}{'median':>9}")
    with tempfile.TemporaryDirectory(prefix="ringscan-density-") as tmp:
        for name, scale, render, pat in runs:
            rig = scaled_rig(scale)
            scan = _simulate(Path(tmp) / f"run{len(name)}_{scale}", scene, rig, pat, **render)
            r = _measure(scan)
            cppb = pat["pitch"] * rig.light.pixel_pitch_mm / (420.0 / rig.camera.K[0, 0])
            print(f"{name:<16}{cppb:>12.2f}{r['samples']:>9}{r['object_pixels_with_sample']:>17.3f}"
                  f"{(r['coverage'] or 0):>9.3f}{r['judged']:>8}{r['mislabelled']:>10}{r['off_by_a_band']:>9}"
                  f"{r['mislabelled_over_1mm']:>13}"
                  f"{r['frac_over_1mm'] * 100:>8.3f}{r['median_mm']:>9.4f}", flush=True)
            import shutil

            shutil.rmtree(scan.folder, ignore_errors=True)


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    sub = p.add_subparsers(dest="cmd", required=True)
    s = sub.add_parser("speed")
    s.add_argument("--scan", default=None)
    s.add_argument("--scene", default=None)
    s.add_argument("--repeats", type=int, default=5)
    a = sub.add_parser("accuracy")
    a.add_argument("--scene", default=None)
    d = sub.add_parser("density")
    d.add_argument("--scene", default=None)
    d.add_argument("--quick", action="store_true", help="fewer runs")
    args = p.parse_args(argv)
    from ringscan.kernels import init_warp

    init_warp()
    {"speed": cmd_speed, "accuracy": cmd_accuracy, "density": cmd_density}[args.cmd](args)
    return 0


if __name__ == "__main__":
    sys.exit(main())
