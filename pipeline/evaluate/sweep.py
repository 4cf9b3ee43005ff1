"""Error and coverage against the number of rings (``ringscan sweep``).

For a scene on the virtual rig, simulate and reconstruct once per ring count
(gray-rings runs over the same annulus with ``bits`` 3..8, and optionally a dense
phase-rings run), interpolate the surface between rings in the camera image
(:func:`interpolate_surface`), and measure it against the truth: surface error,
coverage, the ring points' own error, and ``min_rings``, the fewest rings that reach
each target error with enough coverage. Writes ``sweep.json``, ``sweep.csv`` and
``sweep.png`` / ``sweep.svg`` (matplotlib). The runs, the interpolation rule and every
figure: docs/dense.md ("ringscan sweep"); why: docs/design.md §1, §16.
"""

from __future__ import annotations

import csv
import io
import logging
import math
import os
import shutil
import tempfile
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from ringscan.pipeline.codecs import gray_rings, phase_rings
from ringscan.pipeline.evaluate.metrics import evaluate_view, point_distances, truth_points, truth_surface
from ringscan.pipeline.formats.atomic import atomic_write_bytes, atomic_write_json
from ringscan.pipeline.formats.images import write_image
from ringscan.pipeline.formats.patterns import PatternSpec, parse_patterns
from ringscan.pipeline.formats.rig import ParallelLight, Rig, default_rig
from ringscan.pipeline.geometry import projector_polar
from ringscan.pipeline.preview.plots import figure_to_image, new_figure, save_figure
from ringscan.pipeline.reconstruct.view import reconstruct_view
from ringscan.pipeline.simulate.scan import simulate_scan
from ringscan.pipeline.simulate.scenes import SceneMesh, make_scene
from ringscan.pipeline.simulate.virtual_rig import RenderSettings

log = logging.getLogger(__name__)

SWEEP_FORMAT = "ringscan.sweep/1"
OBJECT_HEIGHT_MM = 0.5
CSV_FIELDS = ("codec", "bits", "pitch", "rings", "rings_on_object", "points", "surface_median_mm", "surface_p95_mm",
              "surface_rms_mm", "coverage", "point_median_mm", "point_p95_mm", "point_frac_over_1mm", "time_s")

__all__ = ["SweepSettings", "run_sweep", "interpolate_surface", "plot_sweep", "sweep_figure", "min_rings", "SWEEP_FORMAT"]


@dataclass(frozen=True)
class SweepSettings:
    """What ``ringscan sweep`` varies and measures."""

    bits: tuple[int, ...] = (3, 4, 5, 6, 7, 8)
    """Band bits of each gray-rings run (2**bits - 1 rings each), 1..10."""
    rho0: float = 8.0
    """Inner radius of the coded annulus (projector px)."""
    radius: float = 520.0
    """Outer radius of the coded annulus (projector px), the same for every run:
    pitch = (radius - rho0) / 2**bits. 520 covers a 78 mm radius on the default rig."""
    sector_bits: int = 6
    """Sector bits of every run (they pick the root, docs/design.md §4)."""
    dense: bool = True
    """Add a phase-rings run: the dense limit."""
    dense_pitch: float = 8.0
    """Fringe pitch (projector px) of the dense run."""
    steps: int = 4
    """Phase steps of the dense run."""
    targets_mm: tuple[float, ...] = (0.5, 0.2, 0.1, 0.05)
    """Surface-error targets for ``min_rings``."""
    min_coverage: float = 0.8
    """Least coverage for a run to meet a target. Ring interpolation cannot reach
    the last band before a silhouette or a shadow, so even dense rings cover
    only ~90 % of a curved object's pixels (the dense codec ~97 %)."""
    max_gap_bands: float = 10.0
    """Longest interpolation bridge in 3D, in band widths (in the light's cross
    section): rings one band apart lie 1 / cos(theta) bands apart on a surface
    sloped theta to the light, so 10 bridges slopes up to ~84 degrees and no
    gap of more than a few missing bands."""

    def __post_init__(self):
        if not self.bits or any(not isinstance(b, (int, np.integer)) or not 1 <= b <= 10 for b in self.bits):
            raise ValueError(f"SweepSettings.bits: expected integers in 1..10, got {self.bits!r}")
        if not self.radius > self.rho0 >= 0:
            raise ValueError(f"SweepSettings: need radius > rho0 >= 0, got rho0 {self.rho0}, radius {self.radius}")
        for b in self.bits:
            if (self.radius - self.rho0) / 2 ** b < 1.0:
                raise ValueError(f"SweepSettings.bits: {b} bits over rho {self.rho0}..{self.radius} give a pitch of "
                                 f"{(self.radius - self.rho0) / 2 ** b:.2f} px, below one projector pixel")
        if not self.targets_mm or any(not t > 0 for t in self.targets_mm):
            raise ValueError(f"SweepSettings.targets_mm: expected positive numbers, got {self.targets_mm!r}")
        if not 0 <= self.min_coverage <= 1 or not self.max_gap_bands > 0:
            raise ValueError("SweepSettings: min_coverage must be in [0, 1] and max_gap_bands > 0")

    def pitch(self, bits: int) -> float:
        return (self.radius - self.rho0) / 2 ** bits


def _band_mm(rig: Rig, pitch: float) -> float:
    """Width of one band at the object (mm)."""
    li = rig.light
    if isinstance(li, ParallelLight):
        return pitch * li.pixel_pitch_mm
    mid = np.array([0.0, 0.0, 0.5 * (rig.volume.z_min + rig.volume.z_max)])
    return pitch * float(np.linalg.norm(li.center - mid)) / float(li.K[0, 0])


def interpolate_surface(uv: np.ndarray, points: np.ndarray, ring: np.ndarray, query_pixel: np.ndarray, *, width: int,
                        height: int, max_gap_mm: float) -> tuple[np.ndarray, np.ndarray]:
    """3D points at query pixels interpolated between ring samples (see the module docstring).

    A pixel between rings j and j + 1 has, of all even-labelled samples, one of
    ring j or j + 1 nearest, and of all odd-labelled samples one of the other: the
    two nearest samples by parity (OpenCV distance transforms with labels, one per
    parity) bracket it when their labels differ by one, the pixel projects
    between them and is no farther from either than they are from each other,
    and they are at most ``max_gap_mm`` apart in 3D. The point is
    then interpolated by the pixel's image distances to the two. Samples with
    ring -1 (dense codecs) at a pixel centre give that pixel its point directly.

    Args:
        uv: (n, 2) sample pixel coordinates.
        points: (n, 3) sample world points.
        ring: (n,) ring labels (-1: dense samples, no ring).
        query_pixel: (m,) linear pixel indices y * width + x.
        width, height: image size.
        max_gap_mm: longest bridge in 3D.

    Returns:
        (X (m, 3) float64, covered (m,) bool); X is 0 where not covered.
    """
    import cv2

    uv = np.asarray(uv, np.float64).reshape(-1, 2)
    P = np.asarray(points, np.float64).reshape(-1, 3)
    ring = np.asarray(ring, np.int64).reshape(-1)
    q = np.asarray(query_pixel, np.int64).reshape(-1)
    m = q.size
    X = np.zeros((m, 3))
    covered = np.zeros(m, bool)
    if uv.shape[0] == 0 or m == 0:
        return X, covered
    qy, qx = np.divmod(q, width)
    cell = np.rint(uv).astype(np.int64)
    inside = (cell[:, 0] >= 0) & (cell[:, 0] < width) & (cell[:, 1] >= 0) & (cell[:, 1] < height)
    lin = cell[:, 1] * width + cell[:, 0]
    # Dense samples: a point per pixel.
    dense = inside & (ring < 0)
    if dense.any():
        owner = np.full(width * height, -1, np.int64)
        owner[lin[dense]] = np.flatnonzero(dense)
        hit = owner[q]
        X[hit >= 0] = P[hit[hit >= 0]]
        covered |= hit >= 0
    nearest = []
    for parity in (0, 1):
        sel = np.flatnonzero(inside & (ring >= 0) & (ring % 2 == parity))
        if sel.size == 0:
            return X, covered
        owner = np.full(width * height, -1, np.int64)
        owner[lin[sel]] = sel  # one sample per pixel cell (the last one)
        img = np.where(owner.reshape(height, width) >= 0, 0, 255).astype(np.uint8)
        _, labels = cv2.distanceTransformWithLabels(img, cv2.DIST_L2, 5, labelType=cv2.DIST_LABEL_PIXEL)
        zero = np.flatnonzero(img.ravel() == 0)
        lab_owner = np.full(int(labels.max()) + 1, -1, np.int64)
        lab_owner[labels.ravel()[zero]] = owner[zero]
        nearest.append(lab_owner[labels.ravel()[q]])
    a, b = nearest
    ok = (a >= 0) & (b >= 0) & ~covered
    a, b = np.where(ok, a, 0), np.where(ok, b, 0)
    ok &= np.abs(ring[a] - ring[b]) == 1
    p = np.stack([qx, qy], -1).astype(np.float64)
    ua, ub = uv[a], uv[b]
    ab = ub - ua
    ok &= (np.sum((p - ua) * ab, axis=1) >= 0) & (np.sum((p - ub) * -ab, axis=1) >= 0)
    ok &= np.linalg.norm(P[a] - P[b], axis=1) <= max_gap_mm
    da = np.linalg.norm(p - ua, axis=1)
    db = np.linalg.norm(p - ub, axis=1)
    span = np.linalg.norm(ab, axis=1)
    ok &= (da <= span) & (db <= span)  # the pixel lies in the lens between the two
    wsum = np.maximum(da + db, 1e-12)
    Xi = (db / wsum)[:, None] * P[a] + (da / wsum)[:, None] * P[b]
    X[ok] = Xi[ok]
    covered |= ok
    return X, covered


def min_rings(runs: list[dict], targets_mm, min_coverage: float) -> dict:
    """Fewest rings (gray-rings runs) whose surface p95 <= target and coverage >= min_coverage."""
    out = {}
    rows = sorted((r for r in runs if r.get("rings")), key=lambda r: r["rings"])
    for t in targets_mm:
        hit = next((r["rings"] for r in rows if r["surface_p95_mm"] is not None and r["surface_p95_mm"] <= t
                    and r["coverage"] >= min_coverage), None)
        out[f"{t:g}"] = hit
    return out


def _run_one(scan_dir: Path, scene, rig: Rig, spec: PatternSpec, render: RenderSettings, device, region: tuple,
             band_mm: float, settings: SweepSettings) -> dict:
    """Simulate and reconstruct one pattern set; its figures against the truth (one row of the sweep).

    Size: a private step of run_sweep: one run's scan folder, scene, rig, pattern set and render settings, and
    what run_sweep works out once for every run (the device, the region of radii compared, the band's width in
    mm) with the sweep's settings.
    """
    t0 = time.perf_counter()
    scan = simulate_scan(scan_dir, scene=scene, rig=rig, patterns=spec, settings=render, device=device,
                         progress=False)
    view = scan.views[0]
    cloud = reconstruct_view(scan, view, device=device)
    ev = evaluate_view(scan, view.name, cloud.points)
    Xt, pix = truth_points(scan, view.name)
    rho = projector_polar(rig, Xt, spec.center)
    zp = float(scan.extra["truth"].get("reference_plane_z", 0.0))
    keep = (rho >= region[0]) & (rho <= region[1])
    if scan.extra["truth"].get("mesh"):
        keep &= Xt[:, 2] - zp > OBJECT_HEIGHT_MM
    pix = pix[keep]
    X, covered = interpolate_surface(cloud.uv, cloud.points, cloud.ring, pix, width=rig.camera.width,
                                     height=rig.camera.height, max_gap_mm=settings.max_gap_bands * band_mm)
    d = point_distances(truth_surface(scan, view.turntable_deg), X[covered])
    on_obj = cloud.points[:, 2] - zp > OBJECT_HEIGHT_MM
    rings = cloud.ring[on_obj]
    return {
        "codec": spec.codec,
        "bits": spec.bits,
        "pitch": spec.pitch,
        "rings": len(spec.ring_radii()) if not spec.layout.dense else None,
        "rings_on_object": int(np.unique(rings[rings >= 0]).size) if not spec.layout.dense else None,
        "points": int(cloud.points.shape[0]),
        "surface_median_mm": float(np.median(d)) if d.size else None,
        "surface_p95_mm": float(np.percentile(d, 95)) if d.size else None,
        "surface_rms_mm": float(np.sqrt(np.mean(d * d))) if d.size else None,
        "coverage": float(covered.mean()) if covered.size else 0.0,
        "point_median_mm": ev["median_mm"],
        "point_p95_mm": ev["p95_mm"],
        "point_frac_over_1mm": ev["frac_over_1mm"],
        "object_pixels": int(pix.size),
        "time_s": time.perf_counter() - t0,
    }


def run_sweep(
    out_dir: str | os.PathLike,
    *,
    scene="sphere",
    rig: Rig | None = None,
    settings: SweepSettings = SweepSettings(),
    render: RenderSettings = RenderSettings(),
    device: str | None = None,
    keep_scans: bool = False,
    progress: bool = True,
    size_mm: float = 80.0,
    up: str = "auto",
) -> dict:
    """Simulate and reconstruct a scene once per ring count; write sweep.json, sweep.csv, sweep.png.

    Args:
        out_dir: output folder (created).
        scene: a scene name, mesh path or ``SceneMesh``.
        rig: the rig (default: the default virtual rig).
        settings: what to vary and the targets.
        render: rendering settings of the virtual rig.
        device: Warp device.
        keep_scans: keep each run's scan folder under ``out_dir/scans`` (else temporary).
        progress: show a progress bar.
        size_mm, up: for a scene given by name or path.

    Returns:
        The sweep result (also written to ``sweep.json``).

    Size: a public function: the output folder and its documented keyword-only options, one per user-facing
    setting (scene, rig, sweep and render settings, device, what to keep and show, the scene's size and up
    axis).
    """
    from ringscan.pipeline.formats.progress import progress_bar


    if not isinstance(settings, SweepSettings):
        raise ValueError(f"settings: expected SweepSettings, got {type(settings).__name__}")
    rig = default_rig() if rig is None else rig
    mesh = scene if isinstance(scene, SceneMesh) else make_scene(scene, size_mm=size_mm, up=up)
    specs = _sweep_patterns(rig, settings)
    big = max(s.pitch for s in specs)
    region = (settings.rho0 + big, settings.radius - big)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    scans_root = out / "scans" if keep_scans else Path(tempfile.mkdtemp(prefix="ringscan-sweep-"))
    runs = []
    t_all = time.perf_counter()
    try:
        for spec in progress_bar(specs, desc=f"sweep {mesh.name}", unit="run", disable=not progress, leave=False):
            name = f"{spec.codec}_{spec.bits}bits_pitch{spec.pitch:g}"
            r = _run_one(scans_root / name, mesh, rig, spec, render, device, region, _band_mm(rig, spec.pitch),
                         settings)
            runs.append(r)
            log.info("%s: %s rings, surface p95 %s mm, coverage %.3f", name, r["rings"], r["surface_p95_mm"],
                     r["coverage"])
            if not keep_scans:
                shutil.rmtree(scans_root / name, ignore_errors=True)
    finally:
        if not keep_scans:
            shutil.rmtree(scans_root, ignore_errors=True)
    result = {
        "format": SWEEP_FORMAT,
        "scene": mesh.name,
        "settings": {k: list(v) if isinstance(v, tuple) else v for k, v in asdict(settings).items()},
        "render": render.to_dict(),
        "region_rho_px": list(region),
        "runs": runs,
        "min_rings": min_rings(runs, settings.targets_mm, settings.min_coverage),
        "time_s": time.perf_counter() - t_all,
    }
    _write_sweep(out, result, mesh.name, settings)
    return result


def _sweep_patterns(rig: Rig, settings: SweepSettings) -> list[PatternSpec]:
    """The pattern sets of a sweep on ``rig``'s projector: gray-rings at each of ``settings.bits`` (one
    ring count each), and phase-rings at the dense pitch where ``settings.dense``."""
    pw, ph = (rig.light.width, rig.light.height) if getattr(rig.light, "width", 0) else (1024, 768)
    center = [(pw - 1) / 2.0, (ph - 1) / 2.0]
    specs = []
    for b in sorted(set(int(x) for x in settings.bits)):
        specs.append(parse_patterns({"codec": gray_rings.NAME, "width": pw, "height": ph, "center": center,
                                     "rho0": settings.rho0, "pitch": settings.pitch(b), "bits": b,
                                     "sector_bits": settings.sector_bits}))
    if settings.dense:
        nb = max(1, math.ceil(math.log2((settings.radius - settings.rho0) / settings.dense_pitch)))
        specs.append(parse_patterns({"codec": phase_rings.NAME, "width": pw, "height": ph, "center": center,
                                     "rho0": settings.rho0, "pitch": settings.dense_pitch, "bits": nb,
                                     "sector_bits": settings.sector_bits, "steps": settings.steps}))
    return specs


def _write_sweep(out: Path, result: dict, scene_name: str, settings: SweepSettings) -> None:
    """Write a sweep's result: sweep.json, sweep.csv (one row per run) and its figure (sweep.png, sweep.svg)."""
    runs = result["runs"]
    atomic_write_json(out / "sweep.json", result)
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=CSV_FIELDS, extrasaction="ignore", lineterminator="\n")
    w.writeheader()
    for r in runs:
        w.writerow({k: ("" if r.get(k) is None else r.get(k)) for k in CSV_FIELDS})
    atomic_write_bytes(out / "sweep.csv", buf.getvalue().encode())
    fig = sweep_figure(runs, title=f"{scene_name}: surface error and coverage vs rings",
                       targets_mm=settings.targets_mm, min_coverage=settings.min_coverage)
    write_image(out / "sweep.png", figure_to_image(fig))
    save_figure(fig, out / "sweep.svg")


# ----------------------------------------------------------------------------- plot


def sweep_figure(runs: list[dict], *, title: str = "", targets_mm=(), min_coverage: float | None = None,
                 size: tuple[int, int] = (960, 600)):
    """The sweep's matplotlib figure: surface error (median, p95; log scale, left
    axis) and coverage (right axis) against the number of rings (log scale), with
    the error targets and the least coverage as dashed lines. Dense runs are drawn
    at the right, labelled ``dense``."""
    from matplotlib.ticker import PercentFormatter

    fig = new_figure(size)
    ax = fig.add_subplot()
    cov_ax = ax.twinx()
    ring_rows = sorted((r for r in runs if r.get("rings")), key=lambda r: r["rings"])
    dense = [r for r in runs if not r.get("rings")]
    xs = [float(r["rings"]) for r in ring_rows]
    xd = (max(xs) * 4.0 if xs else 1.0) if dense else None
    c_med, c_p95, c_cov = "tab:blue", "tab:red", "tab:green"

    def series(axis, key, color, marker, label):
        pts = [(x, r[key]) for r, x in zip(ring_rows, xs)
               if r.get(key) is not None and (key == "coverage" or r[key] > 0)]
        if pts:
            axis.plot(*zip(*pts), color=color, marker=marker, lw=2, label=label)
        for r in dense:
            v = r.get(key)
            if v is not None and (key == "coverage" or v > 0):
                axis.plot([xd], [v], color=color, marker=marker, ls="none", ms=9, mfc="white", mew=2)

    series(ax, "surface_p95_mm", c_p95, "s", "surface error p95")
    series(ax, "surface_median_mm", c_med, "o", "surface error median")
    series(cov_ax, "coverage", c_cov, "^", "coverage (right axis)")
    for t in targets_mm:
        ax.axhline(float(t), color="0.35", ls="--", lw=1)
        ax.annotate(f"target {float(t):g} mm", (0.005, float(t)), xycoords=("axes fraction", "data"),
                    textcoords="offset points", xytext=(2, 2), fontsize=8, color="0.3")
    if min_coverage is not None:
        cov_ax.axhline(float(min_coverage), color=c_cov, ls=":", lw=1)
        cov_ax.annotate(f"least coverage {100 * float(min_coverage):g} %", (0.995, float(min_coverage)),
                        xycoords=("axes fraction", "data"), textcoords="offset points", xytext=(-2, 2),
                        ha="right", fontsize=8, color=c_cov)
    ax.set_xscale("log", base=2)
    ax.set_yscale("log")
    ticks = [*xs, *([xd] if xd else [])]
    ax.set_xticks(ticks, [*(f"{int(x)}" for x in xs), *(["dense"] if xd else [])])
    ax.minorticks_off()
    ax.set_xlabel("number of rings (log scale)")
    ax.set_ylabel("surface error, mm (log scale)")
    cov_ax.set_ylabel("coverage", color=c_cov)
    cov_ax.set_ylim(0.0, 1.05)
    cov_ax.yaxis.set_major_formatter(PercentFormatter(1.0))
    cov_ax.tick_params(axis="y", colors=c_cov)
    ax.grid(True, which="major", color="0.9")
    handles = [*ax.get_legend_handles_labels()[0], *cov_ax.get_legend_handles_labels()[0]]
    if handles:
        ax.legend(handles=handles, loc="lower left", fontsize=9)
    if title:
        ax.set_title(title)
    return fig


def plot_sweep(runs: list[dict], *, title: str = "", targets_mm=(), min_coverage: float | None = None,
               size: tuple[int, int] = (960, 600)) -> np.ndarray:
    """:func:`sweep_figure` as a BGR uint8 image of ``size`` (width, height)."""
    return figure_to_image(sweep_figure(runs, title=title, targets_mm=targets_mm, min_coverage=min_coverage,
                                        size=size))
