"""The cone model (a perspective projector) end to end on the virtual rig, next to
the paper's parallel light (docs/accuracy.md, "The cone model").

For each scene (Spot from ../shared/data/models when present, and the sphere) and
each light it simulates one view with gray-rings (7 bits, pitch 4 px, 6 sector
bits), reconstructs it and prints the error against the ground truth: median,
RMS, p95, the share of points over 1 mm, coverage of the lit surface, and the
roots dropped by reason. The lights:

- ``parallel``: the default rig's collimated light (cylinders; the paper's model);
- ``perspective``: ``ringscan simulate --light perspective``, a 1024x768
  projector 600 mm above the plane looking straight down (cones, no distortion);
- ``perspective-tilted``: the same projector moved to the camera's far side
  and tilted 15 degrees toward the object, with lens distortion (k1 = -0.08,
  k2 = 0.05, p1 = 0.001): oblique cones, the rings are not circles on the plane,
  and every ring root goes through the kernels' Newton refinement for the
  projector's distortion. Its rig file is written to the work folder, so the
  case can be rerun with ``ringscan simulate --rig``.

The virtual rig renders with the same camera and light code that the
reconstruction triangulates with, so these figures show the cone path's
self-consistency (decoding, root choice, Newton refinement, numerics), not a
real projector's calibration.

    python benchmarks/cone_accuracy.py [--model PATH] [--out DIR] [--device cpu]
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import tempfile
import time
from pathlib import Path

import numpy as np

from ringscan.pipeline.evaluate.metrics import evaluate_recon
from ringscan.pipeline.formats.patterns import parse_patterns
from ringscan.pipeline.formats.rig import default_rig, look_at, save_rig
from ringscan.pipeline.reconstruct.scan import reconstruct_scan
from ringscan.pipeline.simulate.scan import simulate_scan

PATTERNS = {"codec": "gray-rings", "width": 1024, "height": 768, "center": [511.5, 383.5], "rho0": 8.0,
            "pitch": 4.0, "bits": 7, "sector_bits": 6}
SHARED_SPOT = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "models" / "odedstein_spot.obj"
TILT_DEG = 15.0
TILTED_DIST = (-0.08, 0.05, 0.001, 0.0, 0.0)


def tilted_perspective_rig():
    """The built-in perspective rig with its projector on the camera's far side
    (+y), tilted TILT_DEG toward the object, 600 mm from (0, 0, 25), with lens
    distortion TILTED_DIST."""
    rig = default_rig(light_model="perspective")
    a = math.radians(TILT_DEG)
    target = np.array([0.0, 0.0, 25.0])
    eye = target + 575.0 * np.array([0.0, math.sin(a), math.cos(a)])
    R, t = look_at(eye, target)
    light = dataclasses.replace(rig.light, R=R, t=t, dist=np.array(TILTED_DIST))
    return dataclasses.replace(rig, light=light)


def lights() -> dict:
    return {"parallel": default_rig(), "perspective": default_rig(light_model="perspective"),
            "perspective-tilted": tilted_perspective_rig()}


def run_case(out: Path, scene: str, rig, device: str | None) -> dict:
    t0 = time.perf_counter()
    scan = simulate_scan(out / "scan", scene=scene, rig=rig, patterns=parse_patterns(PATTERNS), progress=False,
                         device=device)
    t1 = time.perf_counter()
    rep = reconstruct_scan(scan, out / "rec", device=device, progress=False)
    t2 = time.perf_counter()
    a = evaluate_recon(out / "rec", scan)["all"]
    return {"points": rep["totals"]["points"], "samples": rep["totals"]["samples"], "median_mm": a["median_mm"],
            "rms_mm": a["rms_mm"], "p95_mm": a["p95_mm"], "over_1mm": a["frac_over_1mm"],
            "coverage": a["coverage_mean"], "dropped": rep["totals"]["dropped"], "simulate_s": t1 - t0,
            "reconstruct_s": t2 - t1}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--model", default=str(SHARED_SPOT) if SHARED_SPOT.exists() else None,
                    help="a mesh file (default: Spot from ../shared/data/models when present)")
    ap.add_argument("--out", default=None, help="work folder (default: a temporary one)")
    ap.add_argument("--device", default="cpu")
    args = ap.parse_args(argv)
    out = Path(args.out or tempfile.mkdtemp(prefix="ringscan-cone-"))
    out.mkdir(parents=True, exist_ok=True)
    save_rig(out / "perspective_tilted_rig.json", tilted_perspective_rig())
    scenes = ([("spot", args.model)] if args.model else []) + [("sphere", "sphere")]
    print(f"work folder {out}; tilted rig: {out / 'perspective_tilted_rig.json'}")
    print(f"{'scene':8}{'light':20}{'points':>9}{'median':>9}{'RMS':>8}{'p95':>8}{'>1mm':>9}{'cover':>8}  dropped")
    rows = []
    for sname, scene in scenes:
        for lname, rig in lights().items():
            r = run_case(out / f"{sname}_{lname}", scene, rig, args.device)
            rows.append({"scene": sname, "light": lname, **r})
            dropped = ", ".join(f"{k} {v}" for k, v in r["dropped"].items() if v)
            print(f"{sname:8}{lname:20}{r['points']:>9}{r['median_mm']:>9.4f}{r['rms_mm']:>8.4f}{r['p95_mm']:>8.4f}"
                  f"{100 * r['over_1mm']:>8.4f}%{100 * r['coverage']:>7.1f}%  {dropped}", flush=True)
    (out / "cone_accuracy.json").write_text(json.dumps(rows, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
