"""The batch report (``OUT/batch_report.json``) and its summary table."""

from __future__ import annotations

import json
from pathlib import Path

from ringscan.pipeline.batch.worker import STAGES, STORAGE_STAGES

__all__ = ["BATCH_REPORT_FORMAT", "summarise", "format_table", "format_calibration_checks", "TIME_FIELDS", "RUN_FIELDS",
           "read_results"]

BATCH_REPORT_FORMAT = "ringscan.batch/1"

TIME_FIELDS = ("time_s", "times_s", "cpu_s", "wall_s", "views_per_s", "first_result_s", "last_result_s",
               "cpu_per_view_s", "workers", "backend", "worker_start_s")
"""Fields of the reports that depend on how the run went (clock, workers), not on its results."""


def summarise(entries: list[dict], *, wall_s: float) -> dict:
    """Totals of a batch: scans per status, views computed, views per second, the per-view time split, and
    ``cpu_per_view_s``: the workers' CPU seconds (every thread) on the scans that computed views, per view
    computed (a worker's start-up not counted, but its first scan's loading of the kernels it launches is; on a
    shared machine it moves far less with the load than the clock does)."""
    status: dict[str, int] = {}
    split = dict.fromkeys((*STAGES, "other"), 0.0)
    computed = 0
    cpu = 0.0
    for e in entries:
        key = "failed" if e.get("status") == "failed" else e.get("status", "?")
        status[key] = status.get(key, 0) + 1
        computed += int(e.get("computed_views", 0))
        if int(e.get("computed_views", 0)):
            cpu += float(e.get("cpu_s", 0.0))
        for k, s in e.get("times_s", {}).items():
            split[k] = split.get(k, 0.0) + float(s)
    per_view = {k: (s / computed if computed else 0.0) for k, s in split.items()}
    return {"scans": len(entries), "status": status, "computed_views": computed,
            "wall_s": wall_s, "views_per_s": computed / wall_s if wall_s > 0 else 0.0,
            "per_view_s": per_view, "cpu_per_view_s": cpu / computed if computed else 0.0}


def format_table(entries: list[dict], totals: dict) -> str:
    """A plain-text table: one line per scan, then the totals and the per-view time split."""
    rows = [("scan", "status", "views", "points", "seconds")]
    for e in entries:
        st = e.get("status", "?")
        if st == "failed":
            st = f"FAILED: {e.get('error', '')}"
        rows.append((e["scan"], st, f"{e.get('computed_views', 0)}/{e.get('views', '-')}", str(e.get("points", "-")),
                     f"{e.get('time_s', 0.0):.2f}"))
    w = [max(len(r[i]) for r in rows[:200]) for i in range(4)]
    w[1] = min(w[1], 60)
    lines = []
    for r in rows:
        lines.append(f"{r[0]:<{w[0]}}  {r[1]:<{w[1]}}  {r[2]:>{w[2]}}  {r[3]:>{w[3]}}  {r[4]:>7}")
    st = ", ".join(f"{n} {k}" for k, n in sorted(totals["status"].items()))
    lines.append(f"{totals['scans']} scan(s): {st}; {totals['computed_views']} view(s) computed in "
                 f"{totals['wall_s']:.1f} s ({totals['views_per_s']:.2f} views/s)")
    if totals["computed_views"]:
        pv = totals["per_view_s"]
        keys = (*STAGES, "other", *(k for k in STORAGE_STAGES if k in pv))
        lines.append("per view (worker seconds): " + ", ".join(f"{k} {pv[k]:.3f}" for k in keys)
                     + (f"; worker CPU {totals['cpu_per_view_s']:.3f} s a view" if totals.get("cpu_per_view_s") else ""))
    ws = totals.get("worker_start_s")
    if ws:
        lines.append(f"worker start-up: {ws['median']:.2f} s (median of {ws['workers']}; max {ws['max']:.2f} s), "
                     "before its first scan; the first scan also loads the kernels it launches")
    return "\n".join(lines)


def format_calibration_checks(entries: list[dict]) -> list[str]:
    """One line per scan with a calibration check (its entry's ``calibration_check``:
    the worst view's), with a warning where the rig file does not fit the images; with three
    rays the projector against the cameras' points (``projector_check``), warned alike."""
    lines = []
    for e in entries:
        c = e.get("calibration_check")
        if not c:
            continue
        what = ("epipolar distance of the camera matches" if c.get("kind") == "epipolar"
                else "ray-ray residual (projector px)")
        line = (f"{e['scan']}: calibration check, worst view {c['view']} ({c['rays']}): {what}: median "
                f"{c['median_px']:.2f} px, p95 {c['p95_px']:.2f} px ({c['samples']} samples)")
        if c.get("views_not_fitting"):
            line += (f"; warning: the rig file does not fit the images in {c['views_not_fitting']} view(s) "
                     "(median above 1 px): check the calibration (docs/calibration.md)")
        p = c.get("projector_check")
        if p:
            line += (f"; projector against the cameras' points, worst view {p['view']}: median "
                     f"{p['residual_px_median']:.2f} px, p95 {p['residual_px_p95']:.2f} px")
            if p.get("views_discounted"):
                line += f", its ray discounted in {p['views_discounted']} view(s)"
            if p.get("views_not_fitting"):
                line += (f"; warning: the projector's calibration does not fit the cameras' in "
                         f"{p['views_not_fitting']} view(s) (median above 1 px): check the calibrations "
                         "(docs/calibration.md)")
        lines.append(line)
    return lines


RUN_FIELDS = ("time_s", "times_s", "resume", "seconds")
"""Fields of a scan's report.json (and fuse_report.json) that record how a run went (clock times, what a
resumed run kept), not what it computed; :func:`read_results` leaves them out."""


def _strip(obj):
    if isinstance(obj, dict):
        return {k: _strip(v) for k, v in obj.items() if k not in RUN_FIELDS}
    if isinstance(obj, list):
        return [_strip(v) for v in obj]
    return obj


def read_results(out_root) -> dict:
    """Everything a batch wrote below ``out_root``, to compare two runs: relative path -> the file's bytes,
    or for a JSON report its content without :data:`RUN_FIELDS` (``batch_report.json`` itself is left out)."""
    out_root = Path(out_root)
    res = {}
    for p in sorted(out_root.rglob("*")):
        if not p.is_file() or p.name == "batch_report.json":
            continue
        rel = p.relative_to(out_root).as_posix()
        res[rel] = _strip(json.loads(p.read_text())) if p.suffix == ".json" else p.read_bytes()
    return res
