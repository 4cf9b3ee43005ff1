"""Accuracy of the core pipeline on the default virtual rig (docs/accuracy.md).

Simulates one view of a mesh (default: Spot from ../shared/data/models, else the
sphere) with gray-rings, 7 bits, pitch 4 px, with and without 6 sector bits, and
the paper's single-shot rings (9 and 30) on the sphere and the terrain;
reconstructs each and prints the error against the ground truth: median, RMS,
p95, the fraction of points over 1 mm, coverage of the lit surface, and the roots
dropped by reason. Single-shot rows add how many samples got a wrong ring label.

    python benchmarks/core_accuracy.py [--model PATH] [--out DIR] [--device cpu]
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path

import numpy as np

from ringscan.pipeline.evaluate.metrics import evaluate_recon
from ringscan.pipeline.formats.patterns import parse_patterns
from ringscan.pipeline.reconstruct.scan import reconstruct_scan
from ringscan.pipeline.simulate.scan import simulate_scan

PROJ = {"width": 1024, "height": 768, "center": [511.5, 383.5]}
SHARED_SPOT = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "models" / "odedstein_spot.obj"


def run_case(name: str, out: Path, scene: str, patterns: dict, device: str | None) -> dict:
    t0 = time.perf_counter()
    scan = simulate_scan(out / name / "scan", scene=scene, patterns=parse_patterns(patterns), progress=False,
                         device=device)
    t1 = time.perf_counter()
    rep = reconstruct_scan(scan, out / name / "rec", device=device, progress=False)
    t2 = time.perf_counter()
    ev = evaluate_recon(out / name / "rec", scan)
    a = ev["all"]
    row = {"case": name, "points": rep["totals"]["points"], "median_mm": a["median_mm"], "rms_mm": a["rms_mm"],
           "p95_mm": a["p95_mm"], "over_1mm": a["frac_over_1mm"], "coverage": a["coverage_mean"],
           "dropped": rep["totals"]["dropped"], "simulate_s": t1 - t0, "reconstruct_s": t2 - t1}
    if patterns["codec"] == "rings":
        row["wrong_labels"] = wrong_ring_labels(scan, out / name / "rec")
    return row


def wrong_ring_labels(scan, rec: Path) -> int:
    """Points whose ring label is not the ring the truth depth puts there."""
    from ringscan.pipeline.evaluate.metrics import truth_rho_at
    from ringscan.pipeline.formats.ply import read_ply

    sp = scan.patterns
    wrong = 0
    for view in scan.views:
        ply = read_ply(rec / f"{view.name}.ply")
        if "u" not in ply or len(ply["ring"]) == 0:
            continue
        uv = np.stack([ply["u"], ply["v"]], axis=1)
        rho_true = truth_rho_at(scan, view.name, uv)
        ok = np.isfinite(rho_true)
        k_true = np.rint((rho_true[ok] - sp.rho0) / sp.pitch)
        wrong += int(np.count_nonzero(k_true != ply["ring"][ok]))
    return wrong


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--model", default=str(SHARED_SPOT) if SHARED_SPOT.exists() else "sphere")
    ap.add_argument("--out", default=None, help="work folder (default: a temporary one)")
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--skip-single-shot", action="store_true")
    args = ap.parse_args(argv)
    out = Path(args.out or tempfile.mkdtemp(prefix="ringscan-accuracy-"))
    gray = {"codec": "gray-rings", **PROJ, "rho0": 8.0, "pitch": 4.0, "bits": 7}
    cases = [("gray7_p4_sectors6", args.model, {**gray, "sector_bits": 6}),
             ("gray7_p4_no_sectors", args.model, {**gray, "sector_bits": 0})]
    if not args.skip_single_shot:
        for scene in ("sphere", "terrain"):
            cases.append((f"rings9_{scene}", scene, {"codec": "rings", **PROJ, "count": 9, "rho0": 40.0,
                                                    "pitch": 40.0, "line_width": 3.0}))
            cases.append((f"rings30_{scene}", scene, {"codec": "rings", **PROJ, "count": 30, "rho0": 12.0,
                                                     "pitch": 12.0, "line_width": 3.0}))
    print(f"model {args.model}; work folder {out}")
    print(f"{'case':22}{'points':>9}{'median':>9}{'RMS':>8}{'p95':>8}{'>1mm':>8}{'cover':>8}{'wrong':>7}  dropped")
    rows = []
    for name, scene, pat in cases:
        r = run_case(name, out, scene, pat, args.device)
        rows.append(r)
        dropped = ", ".join(f"{k} {v}" for k, v in r["dropped"].items() if v)
        print(f"{name:22}{r['points']:>9}{r['median_mm']:>9.4f}{r['rms_mm']:>8.3f}{r['p95_mm']:>8.4f}"
              f"{100 * r['over_1mm']:>7.3f}%{100 * r['coverage']:>7.1f}%{r.get('wrong_labels', ''):>7}  {dropped}",
              flush=True)
    (out / "core_accuracy.json").write_text(json.dumps(rows, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
