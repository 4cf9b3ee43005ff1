"""Where do a reconstruction's predicted sigmas fail? One condition of ``sigma_honesty.py`` taken apart.

Reads a scan with its truth and a reconstruction of it (the folders ``sigma_honesty.py --out DIR`` leaves:
``DIR/<condition>/scan`` and ``DIR/<condition>/<constraint>``) and prints, for the object (points above
``--object-z`` mm, as sigma_honesty's ``(object)`` rows) and for the rest:

- by octile of the predicted sigma: the share beyond 3 sigma, the median |e|/sigma, the median sigma and the
  errors' robust scale (1.4826 x their median |e|): a floor the model lacks shows as errors that stay put
  while sigma falls;
- how the errors of nearby points correlate (same ring and across rings, by camera distance): a smooth bias
  (light bounced onto the surface) correlates, a per-sample noise does not;
- the error model's tile factors (report.json ``regions``) against the factor each 32 px tile would need
  for its points' median |e|/sigma to be a Gaussian's (the truth's, so an upper bound on what any fit from the
  frames could do): the tiles' shortfall, and what the beyond-3-sigma share would be with the truth's factors;
- by fifth of each point's camera noise as its frames show it (``kernels.sample_light.sample_pair_noise``,
  which the sigmas already take where it is above the view's median: docs/reconstruction.md, "Honest sigma"):
  the share beyond 3 sigma and the median |e|/sigma; a noise the sigmas still miss shows as a rise with it.

The errors are along camera 1's ray, as ``evaluate.metrics`` measures them for sigma.

    python benchmarks/sigma_breakdown.py DIR/corner-interreflection [--constraint rings] [--object-z 0.5]
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from ringscan.pipeline.evaluate.metrics import ray_errors, truth_surface
from ringscan.pipeline.formats.ply import read_ply
from ringscan.pipeline.formats.scan import load_scan
from ringscan.pipeline.reconstruct.error_scale import REGION_PX, region_scale

GAUSS_MEDIAN_RATIO = 0.6745
"""Median |e|/sigma of a Gaussian."""


def octile_rows(s: np.ndarray, e: np.ndarray) -> list[dict]:
    """By octile of the predicted sigma ``s`` (errors ``e``, same units): share beyond 3 sigma, median
    |e|/sigma, median sigma, the errors' robust scale (1.4826 x median |e|)."""
    r = np.abs(e) / s
    at = np.digitize(s, np.quantile(s, np.linspace(0, 1, 9))[1:-1])
    return [{"beyond_3": float(np.mean(r[at == i] > 3)), "ratio": float(np.median(r[at == i])),
             "sigma": float(np.median(s[at == i])), "scale": float(1.4826 * np.median(np.abs(e[at == i])))}
            for i in range(8)]


def octiles(name: str, s: np.ndarray, e: np.ndarray) -> None:
    r = np.abs(e) / s
    print(f"{name}: {s.size} points, {np.mean(r > 3) * 100:.2f} % beyond 3 sigma, median |e|/sigma {np.median(r):.2f}")
    print("  sigma octile | beyond 3 sigma | median |e|/sigma | median sigma um | error scale um")
    for i, row in enumerate(octile_rows(s, e)):
        print(f"  {i + 1}            | {row['beyond_3'] * 100:5.1f} %        | {row['ratio']:.2f}             "
              f"| {row['sigma'] * 1e3:7.1f}         | {row['scale'] * 1e3:7.1f}")


def correlations(e: np.ndarray, uv: np.ndarray, ring: np.ndarray) -> None:
    tree = cKDTree(uv)
    print("  errors of nearby points: correlation (same ring / across rings)")
    for rad in (1.5, 4.0, 10.0):
        pairs = tree.query_pairs(rad, output_type="ndarray")
        if len(pairs) > 2_000_000:
            pairs = pairs[np.random.default_rng(0).choice(len(pairs), 2_000_000, replace=False)]
        a, b = pairs[:, 0], pairs[:, 1]
        same = ring[a] == ring[b]
        cells = [f"{np.corrcoef(e[a[m]], e[b[m]])[0, 1]:.2f} ({m.sum()} pairs)" if m.sum() > 100 else "-"
                 for m in (same, ~same)]
        print(f"  within {rad:4.1f} px: {cells[0]} / {cells[1]}")


def tile_factors(s: np.ndarray, e: np.ndarray, uv: np.ndarray, regions: dict | None) -> dict:
    """Each ``REGION_PX`` tile (>= 30 points) of camera pixels ``uv``: the variance factor the model's
    ``regions`` gave it and the one its errors ask beyond the sigmas ``s`` (for a Gaussian's median |e|/sigma,
    at least 1); the sigmas with those factors."""
    model = region_scale(regions, uv)
    key = np.floor(uv / REGION_PX).astype(np.int64)
    tile = key[:, 0] * 1_000_003 + key[:, 1]
    need, have = [], []
    s_truth = s.copy()
    for t in np.unique(tile):
        m = tile == t
        if m.sum() < 30:
            continue
        f = max(1.0, (np.median(np.abs(e[m]) / s[m]) / GAUSS_MEDIAN_RATIO) ** 2)
        need.append(f)
        have.append(model[m][0])
        s_truth[m] = s[m] * np.sqrt(f)
    return {"need": np.asarray(need), "have": np.asarray(have), "sigma_truth": s_truth}


def tiles(s: np.ndarray, e: np.ndarray, uv: np.ndarray, regions: dict | None) -> None:
    t = tile_factors(s, e, uv, regions)
    need, have = t["need"], t["have"]
    if need.size == 0:
        return
    r = np.abs(e) / t["sigma_truth"]
    print(f"  tiles of {REGION_PX} px (>= 30 points): {need.size}; the model gave {np.mean(have > 1) * 100:.0f} % of them "
          f"a factor (median {np.median(have[have > 1]) if (have > 1).any() else 1:.2f}); the truth asks, beyond the "
          f"model's sigma, a median {np.median(need):.2f} (p90 {np.percentile(need, 90):.2f}) on the variance")
    print(f"  with the truth's tile factors: {np.mean(r > 3) * 100:.2f} % beyond 3 sigma, median |e|/sigma "
          f"{np.median(r):.2f} (what a per-tile factor could reach at best)")


def noise_rows(noise: np.ndarray, s: np.ndarray, e: np.ndarray) -> list[dict]:
    """By fifth of the measured frame ``noise`` (grey levels): share beyond 3 sigma, median |e|/sigma, median
    noise."""
    r = np.abs(e) / s
    at = np.digitize(noise, np.quantile(noise, np.linspace(0, 1, 6))[1:-1])
    return [{"beyond_3": float(np.mean(r[at == i] > 3)), "ratio": float(np.median(r[at == i])),
             "noise": float(np.median(noise[at == i]))} for i in range(5)]


def view_noise(scan, uv: np.ndarray) -> np.ndarray | None:
    """Each point's frame noise (grey levels) read from the view's frames at its camera position, or None for
    a codec without band pairs."""
    import warp as wp

    from ringscan.kernels import init_warp
    from ringscan.kernels.sample_light import sample_pair_noise
    from ringscan.pipeline.codecs.angle_code import noise_pairs
    from ringscan.pipeline.formats.patterns import frame_names
    from ringscan.pipeline.formats.scan import read_view_frames

    names = frame_names(scan.patterns)
    if "white" not in names or scan.patterns.bits < 2 or "gray_0" not in names:
        return None
    init_warp()
    frames = wp.array(read_view_frames(scan, scan.views[0]), device="cpu")
    return sample_pair_noise(frames, wp.array(uv.astype(np.float32), dtype=wp.vec2, device="cpu"),
                             white=names.index("white"), black=names.index("black"),
                             pairs=noise_pairs(scan.patterns)).numpy().astype(np.float64)


def noises(noise: np.ndarray, s: np.ndarray, e: np.ndarray) -> None:
    print("  frame noise fifth | beyond 3 sigma | median |e|/sigma | median noise (levels)")
    for i, row in enumerate(noise_rows(noise, s, e)):
        print(f"  {i + 1}                 | {row['beyond_3'] * 100:5.1f} %        | {row['ratio']:.2f}             "
              f"| {row['noise']:.2f}")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("condition", type=Path, help="a condition's folder of sigma_honesty.py --out DIR (scan/ inside)")
    ap.add_argument("--constraint", default="rings", help="the reconstruction's folder name (default rings)")
    ap.add_argument("--object-z", type=float, default=0.5, help="object: points above this world z, mm (0.5)")
    a = ap.parse_args(argv)
    rec = a.condition / a.constraint
    if not (a.condition / "scan" / "scan.json").is_file() or not (rec / "report.json").is_file():
        print(f"sigma_breakdown: {a.condition}: expected scan/scan.json and {a.constraint}/report.json "
              "(a condition's folder of sigma_honesty.py --out DIR)", file=sys.stderr)
        return 1
    scan = load_scan(a.condition / "scan")
    view = json.loads((rec / "report.json").read_text())["views"][0]
    ply = read_ply(rec / view["ply"])
    P = np.stack([ply["x"], ply["y"], ply["z"]], -1).astype(np.float64)
    s = np.asarray(ply["sigma"], np.float64)
    cam = scan.rig.camera
    centre = -np.asarray(cam.R, np.float64).T @ np.asarray(cam.t, np.float64)
    e = ray_errors(truth_surface(scan, scan.views[0].turntable_deg), P, centre)
    uv = np.stack([ply["u"], ply["v"]], -1).astype(np.float64)
    ring = np.asarray(ply["ring"])
    ok = np.isfinite(e) & (s > 0)
    model = view.get("error_model") or view.get("calibration", {}).get("error_model") or {}
    noise = view_noise(scan, uv)
    for name, m in (("object", ok & (P[:, 2] > a.object_z)), ("the rest", ok & ~(P[:, 2] > a.object_z))):
        if m.sum() < 100:
            continue
        octiles(name, s[m], e[m])
        correlations(e[m], uv[m], ring[m])
        tiles(s[m], e[m], uv[m], model.get("regions"))
        if noise is not None:
            noises(noise[m], s[m], e[m])
    return 0


if __name__ == "__main__":
    sys.exit(main())
