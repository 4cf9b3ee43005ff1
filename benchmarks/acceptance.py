"""Whole-scan acceptance runs on the default virtual rig at full size (1280x1024), with their bounds.

These were tests; each takes tens of seconds on a 2-core machine, so they run here and the
suite keeps a smaller case of every behaviour (named in each case's docstring). Every case
prints its figures, then one line per bound: ``ok`` or ``MISSED``. Exit status 1 when any
bound is missed, 0 otherwise.

    python benchmarks/acceptance.py                 # every case (~3 minutes on two cores)
    python benchmarks/acceptance.py --only phase-rings-default-rig
    python benchmarks/acceptance.py --list

Scenes: Spot from ../shared/data/models (``RINGSCAN_SHARED_DATA`` overrides the folder); a case
whose model is missing fails (it is no acceptance run without it).
"""

from __future__ import annotations

import argparse
import json
import operator
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from ringscan.pipeline.evaluate.metrics import evaluate_recon, truth_points
from ringscan.pipeline.formats.patterns import parse_patterns
from ringscan.pipeline.formats.ply import read_ply
from ringscan.pipeline.formats.rig import default_rig
from ringscan.pipeline.reconstruct.scan import reconstruct_scan
from ringscan.pipeline.simulate.scan import simulate_scan

ROOT = Path(__file__).resolve().parents[1]
SHARED_DATA = Path(os.environ.get("RINGSCAN_SHARED_DATA", ROOT.parent / "shared" / "data"))
PROJ = {"width": 1024, "height": 768, "center": [511.5, 383.5]}
OPS = {"<=": operator.le, ">=": operator.ge, "<": operator.lt, ">": operator.gt}


def spot() -> str:
    model = SHARED_DATA / "models" / "odedstein_spot.obj"
    if not model.is_file():
        raise SystemExit(f"acceptance: model not found: {model} (set RINGSCAN_SHARED_DATA)")
    return str(model)


def lit_object_fraction(scan, view_name: str, u, v) -> float:
    """Of the pixels that see the object lit (truth, > 0.5 mm above the plane), the share with a point."""
    X, pix = truth_points(scan, view_name)
    obj = pix[X[:, 2] > 0.5]
    w = scan.rig.camera.width
    have = np.zeros(scan.rig.camera.width * scan.rig.camera.height, bool)
    have[np.rint(v).astype(int) * w + np.rint(u).astype(int)] = True
    return float(have[obj].mean())


def _view_figures(scan, rec: Path) -> tuple[dict, dict]:
    rep = reconstruct_scan(scan, rec, progress=False)
    res = evaluate_recon(rec, scan)["views"]["view_000"]
    return rep, res


def case_gray_rings_default_rig(work: Path) -> list:
    """gray-rings, 7 bits, pitch 4 px, Spot on the default rig: with 6 sector bits median <= 0.03 mm,
    <= 0.3 % over 1 mm, >= 95 % of the lit surface; without sector bits the ambiguous roots are
    counted (> 1000) and dropped, not guessed (<= 0.3 % over 1 mm).
    Suite: tests/pipeline/reconstruct/test_reconstruct.py (a 320x256 camera, the same codec; accuracy,
    drop counts), tests/pipeline/reconstruct/test_rings_and_angle.py (ambiguous roots counted)."""
    checks = []
    for sb in (6, 0):
        spec = parse_patterns({"codec": "gray-rings", **PROJ, "rho0": 8.0, "pitch": 4.0, "bits": 7, "sector_bits": sb})
        scan = simulate_scan(work / f"spot{sb}" / "scan", scene=spot(), patterns=spec, progress=False)
        rep, v = _view_figures(scan, work / f"spot{sb}" / "rec")
        print(json.dumps({"sector_bits": sb, **{k: v[k] for k in ("points", "median_mm", "p95_mm", "frac_over_1mm",
                                                                  "coverage")},
                          "ambiguous": rep["views"][0]["dropped"]["ambiguous"]}))
        if sb:
            checks += [(f"sectors {sb}: median_mm", v["median_mm"], "<=", 0.03),
                       (f"sectors {sb}: frac_over_1mm", v["frac_over_1mm"], "<=", 0.003),
                       (f"sectors {sb}: coverage", v["coverage"], ">=", 0.95),
                       (f"sectors {sb}: points", rep["totals"]["points"], ">", 50000)]
        else:
            checks += [("no sectors: ambiguous roots dropped", rep["views"][0]["dropped"]["ambiguous"], ">", 1000),
                       ("no sectors: frac_over_1mm", v["frac_over_1mm"], "<=", 0.003)]
    return checks


def case_phase_rings_default_rig(work: Path) -> list:
    """phase-rings, 4 steps, pitch 8 px, 6 sector bits, Spot on the default rig with camera gamma 2.2:
    >= 90 % of the lit object pixels become points, median <= 0.006 mm, p95 <= 0.05 mm, <= 0.3 % over
    1 mm; the gamma-2.2 median at most 1.3x the same scene's at gamma 1.0 (the camera's noise,
    linearised, is what is left).
    Suite: tests/pipeline/codecs/test_phase_rings.py (a 320x256 crop of the same rig: accuracy, lit
    pixels, response modes, gamma estimate)."""
    spec = parse_patterns({"codec": "phase-rings", **PROJ, "rho0": 8.0, "pitch": 8.0, "bits": 6, "sector_bits": 6,
                           "steps": 4})
    res = {}
    for g in (2.2, 1.0):
        scan = simulate_scan(work / f"phase{g}" / "scan", scene=spot(), rig=default_rig(gamma=g), patterns=spec,
                             progress=False)
        _, v = _view_figures(scan, work / f"phase{g}" / "rec")
        ply = read_ply(work / f"phase{g}" / "rec" / "view_000.ply")
        v["lit_object_fraction"] = lit_object_fraction(scan, "view_000", ply["u"], ply["v"])
        print(json.dumps({"camera_gamma": g, **{k: v[k] for k in ("points", "median_mm", "p95_mm", "frac_over_1mm",
                                                                  "lit_object_fraction")}}))
        res[g] = v
    r = res[2.2]
    return [("gamma 2.2: lit_object_fraction", r["lit_object_fraction"], ">=", 0.90),
            ("gamma 2.2: median_mm", r["median_mm"], "<=", 0.006),
            ("gamma 2.2: p95_mm", r["p95_mm"], "<=", 0.05),
            ("gamma 2.2: frac_over_1mm", r["frac_over_1mm"], "<=", 0.003),
            ("median gamma 2.2 / gamma 1.0", r["median_mm"] / res[1.0]["median_mm"], "<=", 1.3)]


def case_single_shot_default_rig(work: Path) -> list:
    """The paper's single-shot rings on the codec's defaults (9 rings; 30 at pitch 12 px; ring 0 at 8 px, a
    loop ~15 camera px across), the sphere and the terrain on the default rig: every ring labelled with its
    true index (none mislabelled; the sphere's 30 rings one short: a ring reached only across a step of
    more than 3 ring pitches is left out), >= 97 % of the line samples kept, one centre anchor, >= 40 % of the
    points and of the object's lit surface on the object, <= 1 % over 1 mm, median < 0.02 mm.
    Suite: tests/pipeline/codecs/test_single_shot.py (the same checks on a 320x256 camera; an object left
    unlabelled on the full-size small-ring scan)."""
    import warp as wp

    from ringscan.pipeline.codecs.single_shot.extract import extract_rings
    from ringscan.pipeline.codecs.single_shot.settings import SingleShotSettings
    from ringscan.pipeline.formats.patterns import default_patterns
    from ringscan.pipeline.formats.scan import read_view_frames

    sys.path.insert(0, str(ROOT))
    from tests.support.rings_truth import truth_rings

    cases = {"defaults-9": {}, "defaults-30": {"count": 30, "pitch": 12.0}, "small-ring-0": {"rho0": 8.0}}
    checks = []
    for scene, case in (("sphere", "defaults-9"), ("sphere", "defaults-30"), ("terrain", "defaults-9"),
                        ("terrain", "defaults-30"), ("sphere", "small-ring-0")):
        name = f"{scene} {case}"
        scan = simulate_scan(work / f"{scene}-{case}" / "scan", scene=scene,
                             patterns=default_patterns("rings", **cases[case]), progress=False)
        frames = read_view_frames(scan, scan.views[0])
        smp, stats = extract_rings(wp.array(frames, device="cpu"), scan, SingleShotSettings(), 2)
        uv, ring = smp.uv.numpy(), smp.ring.numpy()
        j, ok, _ = truth_rings(scan, "view_000", uv)
        _, v = _view_figures(scan, work / f"{scene}-{case}" / "rec")
        ply = read_ply(work / f"{scene}-{case}" / "rec" / "view_000.ply")
        on_object = float(np.mean(ply["z"] > 0.5))
        print(json.dumps({"case": name, **{k: v[k] for k in ("points", "median_mm", "p95_mm", "frac_over_1mm",
                                                             "coverage_object")}, "on_object": on_object}))
        checks += [(f"{name}: samples with a wrong ring label", int(np.sum(ring[ok] != j[ok])), "<=", 0),
                   (f"{name}: rings labelled other than 0..count-1",
                    len(set(np.unique(ring).tolist()) - set(range(scan.patterns.count))), "<=", 0),
                   # a ring reached only across a 3D step of more than 3 ring pitches is left unlabelled
                   # (docs/single_shot.md): on the sphere's steep rim at 30 rings one is, where 2 of the 4
                   # such links had been wrong with 8 pitches allowed
                   (f"{name}: rings missing",
                    len(set(range(scan.patterns.count)) - set(np.unique(ring).tolist())), "<=",
                    1 if case == "defaults-30" and scene == "sphere" else 0),
                   (f"{name}: samples / line samples", stats["samples"] / stats["line_samples"], ">=", 0.97),
                   (f"{name}: centre anchors", stats["anchors_centre"], ">=", 1),
                   (f"{name}: object unlabelled", int("object_unlabelled" in stats), "<=", 0),
                   (f"{name}: samples labelled off the plane / samples",
                    stats["samples_labelled_off_plane"] / stats["samples"], ">=", 0.4),
                   (f"{name}: points on the object", on_object, ">=", 0.4),
                   (f"{name}: coverage of the object", v["coverage_object"], ">=", 0.4),
                   (f"{name}: frac_over_1mm", v["frac_over_1mm"], "<=", 0.01),
                   (f"{name}: median_mm", v["median_mm"], "<", 0.02)]
    return checks


def case_gray_rings_pitch_2(work: Path) -> list:
    """gray-rings at pitch 2 px (7 bits, 6 sector bits), Spot on the default rig: no point more than 1 mm
    off from a wrong ring label, at most 0.1 % of the judged points mislabelled, at most 0.3 % over 1 mm.
    Suite: tests/pipeline/codecs/test_high_density.py (labels at pitch 2 under defocus and noise)."""
    from ringscan.pipeline.evaluate.metrics import evaluate_view, truth_rho_at
    from ringscan.pipeline.reconstruct.view import reconstruct_view

    spec = parse_patterns({"codec": "gray-rings", **PROJ, "rho0": 8.0, "pitch": 2.0, "bits": 7, "sector_bits": 6})
    scan = simulate_scan(work / "scan", scene=spot(), patterns=spec, progress=False)
    cloud = reconstruct_view(scan, scan.views[0], device="cpu")
    ev, d = evaluate_view(scan, "view_000", cloud.points, return_distances=True)
    rt = truth_rho_at(scan, "view_000", cloud.uv)
    judged = np.isfinite(rt)
    wrong = judged & (np.rint((rt - spec.rho0) / spec.pitch) != cloud.ring)
    print(json.dumps({"points": len(d), "judged": int(judged.sum()), "mislabelled": int(wrong.sum()),
                      "mislabelled_over_1mm": int(np.sum(wrong & (d > 1))), "frac_over_1mm": ev["frac_over_1mm"],
                      "median_mm": ev["median_mm"]}))
    return [("points", len(d), ">", 50000),
            ("judged / points", judged.sum() / len(d), ">", 0.9),
            ("mislabelled and over 1 mm off", int(np.sum(wrong & (d > 1.0))), "<=", 0),
            ("mislabelled / judged", wrong.sum() / judged.sum(), "<=", 1e-3),
            ("frac_over_1mm", ev["frac_over_1mm"], "<=", 0.003)]


def case_rational_lenses(work: Path) -> list:
    """OpenCV's rational lens (8 coefficients, CALIB_RATIONAL_MODEL) on the camera and on a perspective
    projector, the sphere on the default rig (gray-rings, 5 bits, pitch 16 px, 4 sector bits): the points as many
    (> 95 %) and as accurate (median within 15 %) as through the same device's 5-coefficient lens, <= 0.3 % over
    1 mm; read with its first 5 coefficients alone the scan is > 3x worse (the terms are used).
    Suite: tests/pipeline/reconstruct/test_reconstruct.py's test_a_rational_lens_is_as_accurate_as_a_five_coefficient_one
    (the same checks on its 320x256 camera with the thin-prism lenses: their 12 coefficients are these 8 and
    s1..s4), tests/kernels/test_geometry.py (the 8-coefficient lens against OpenCV's projection)."""
    import dataclasses
    import shutil

    from ringscan.pipeline.formats.scan import load_scan, save_scan

    sys.path.insert(0, str(ROOT))
    from tests.support.reconstruct_rig import PROJECTOR_LENS, WIDE_LENS

    spec = parse_patterns({"codec": "gray-rings", **PROJ, "rho0": 8.0, "pitch": 16.0, "bits": 5, "sector_bits": 4})

    def lens_rig(device, dist):
        rig = default_rig()
        if device == "camera":
            return dataclasses.replace(rig, camera=dataclasses.replace(rig.camera, dist=np.array(dist, float)))
        li = default_rig(light_model="perspective").light
        return dataclasses.replace(rig, light=dataclasses.replace(li, dist=np.array(dist, float)))

    def figures(name, rig=None, scan=None):
        if scan is None:
            scan = simulate_scan(work / name / "scan", scene="sphere", rig=rig, patterns=spec, progress=False)
        rep = reconstruct_scan(scan, work / name / "rec", progress=False)
        return scan, {**evaluate_recon(work / name / "rec", scan)["all"], "points": rep["totals"]["points"]}

    checks = []
    for device, wide_dist in (("camera", WIDE_LENS["rational"]), ("light", PROJECTOR_LENS["rational"])):
        five_dist = list(default_rig().camera.dist) if device == "camera" else [0.0] * 5
        _, five = figures(f"{device}-five", lens_rig(device, five_dist))
        scan, wide = figures(f"{device}-rational", lens_rig(device, wide_dist))
        dev = getattr(scan.rig, device)
        assert len(dev.dist) == 8, dev.dist
        # the same frames, read with the lens's first 5 coefficients alone
        cut = dataclasses.replace(scan, rig_ref=None, folder=work / f"{device}-cut" / "scan",
                                  rig=dataclasses.replace(scan.rig, **{device: dataclasses.replace(dev, dist=dev.dist[:5])}))
        shutil.copytree(scan.folder, cut.folder)
        save_scan(cut)
        _, first5 = figures(f"{device}-cut", scan=load_scan(cut.folder))
        print(json.dumps({"device": device, **{f"{k}_{n}": f[k] for n, f in (("five", five), ("rational", wide),
                                                                            ("first5", first5))
                                               for k in ("points", "median_mm", "frac_over_1mm")}}))
        checks += [(f"{device}: rational points / five-coefficient points", wide["points"] / five["points"], ">", 0.95),
                   (f"{device}: rational median / five-coefficient median", wide["median_mm"] / five["median_mm"],
                    "<", 1.15),
                   (f"{device}: rational frac_over_1mm", wide["frac_over_1mm"], "<", 0.003),
                   (f"{device}: first-5 median / rational median", first5["median_mm"] / wide["median_mm"], ">", 3.0)]
    return checks


CASES = {
    "gray-rings-default-rig": case_gray_rings_default_rig,
    "gray-rings-pitch-2": case_gray_rings_pitch_2,
    "phase-rings-default-rig": case_phase_rings_default_rig,
    "rational-lenses": case_rational_lenses,
    "single-shot-default-rig": case_single_shot_default_rig,
}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--only", nargs="+", choices=sorted(CASES), help="run these cases only")
    ap.add_argument("--list", action="store_true", help="name the cases and what each checks, then stop")
    ap.add_argument("--work", metavar="DIR", help="keep the scans in DIR (default: a temporary folder)")
    args = ap.parse_args(argv)
    if args.list:
        for name, fn in CASES.items():
            print(f"{name}: {' '.join(fn.__doc__.split())}")
        return 0
    missed = 0
    with tempfile.TemporaryDirectory(prefix="acceptance_") as tmp:
        base = Path(args.work) if args.work else Path(tmp)
        for name in args.only or CASES:
            t0 = time.perf_counter()
            print(f"== {name}")
            for what, value, op, bound in CASES[name](base / name):
                ok = OPS[op](value, bound)
                missed += not ok
                print(f"  {'ok    ' if ok else 'MISSED'} {what} = {value:.6g} ({op} {bound:g})")
            print(f"  ({time.perf_counter() - t0:.1f} s)")
    print(f"{missed} bound(s) missed" if missed else "every bound met")
    return 1 if missed else 0


if __name__ == "__main__":
    sys.exit(main())
