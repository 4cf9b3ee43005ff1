"""Does a capture through the hardware layer reconstruct as well as a simulated scan?

Simulates a scan of a scene with the virtual rig (``simulate_scan``, which also
writes the ground truth), captures the same scene through the whole hardware
path (emulated GRBL turntable and serial projector on pseudo-terminals, the real
drivers, the virtual camera, the capture sequence), reconstructs both with
``reconstruct_scan`` and measures both against the simulated scan's truth.
The two differ only in sensor noise, so their figures should agree.

    python benchmarks/capture_vs_simulate.py [--views 8] [--scene terrain] [--small]
        [--device cpu] [--out DIR] [--live]

Default: the default rig (1280x1024 camera) and the 28-frame gray-rings set
(7 band bits, 6 sector bits), 8 views: the issue's "8 views x 28 frames".
``--small``: a 320x256 camera and a 12-frame set, for a quick run.
Prints one line per scan (make_s: seconds to simulate / capture it, 0 when reused
from --out; recon_s: seconds to reconstruct) and the ratios captured / simulated.
``--live``: captures the scene once more with each view reconstructed while the
next is captured (``ringscan capture --reconstruct``), checks that it gives the same
points, and prints its wall time against capture-then-reconstruct of the same run.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import tempfile
import time
from pathlib import Path


def small_rig():
    from ringscan.pipeline.formats.rig import default_rig

    rig = default_rig()
    cam = rig.camera
    K = cam.K.copy()
    K[0, 0] = K[1, 1] = cam.K[0, 0] * 0.25
    K[0, 2], K[1, 2] = 159.5, 127.5
    return dataclasses.replace(rig, camera=dataclasses.replace(cam, width=320, height=256, K=K))


def patterns_for(small: bool):
    from ringscan.pipeline.formats.patterns import parse_patterns

    if small:
        d = {"codec": "gray-rings", "width": 1024, "height": 768, "center": [511.5, 383.5], "rho0": 8.0,
             "pitch": 40.0, "bits": 3, "sector_bits": 2}
    else:
        d = {"codec": "gray-rings", "width": 1024, "height": 768, "center": [511.5, 383.5], "rho0": 8.0,
             "pitch": 4.0, "bits": 7, "sector_bits": 6}
    return parse_patterns(d, source="benchmark")


def capture_emulated(out: Path, rig, patterns, scene, views: int, *, seed: int, device, size_mm: float = 80.0,
                     on_view=None):
    """Capture ``views`` views of ``scene`` through the emulated rig and the real drivers."""
    from ringscan.hardware.capture.sequence import CaptureSettings, capture_scan
    from ringscan.hardware.devices.grbl import GrblTurntable
    from ringscan.hardware.devices.projector import SerialProjector
    from ringscan.hardware.emulators.rig import EmulatedRig
    from ringscan.pipeline.formats.patterns import frame_names

    settings = CaptureSettings(turntable_settle_s=0.0, projector_settle_s=0.0)
    with EmulatedRig(rig, patterns, scene, time_scale=1000.0, seed=seed, size_mm=size_mm, device=device) as emu:
        tt = GrblTurntable(emu.turntable_port)
        pj = SerialProjector(emu.projector_port, expect_names=frame_names(patterns))
        try:
            return capture_scan(out, camera=emu.camera, projector=pj, turntable=tt, rig=rig, patterns=patterns,
                                views=views, settings=settings, progress=False, on_view=on_view)
        finally:
            tt.close()
            pj.close()


def measure(scan_dir: Path, truth_scan: Path, recon_dir: Path, device) -> dict:
    """Reconstruct a scan and measure it against the truth of ``truth_scan``."""
    from ringscan.pipeline.evaluate.metrics import evaluate_recon
    from ringscan.pipeline.reconstruct.scan import reconstruct_scan

    t0 = time.perf_counter()
    rep = reconstruct_scan(scan_dir, recon_dir, device=device, progress=False)
    dt = time.perf_counter() - t0
    ev = evaluate_recon(recon_dir, truth_scan)
    a = ev["all"]
    return {"points": int(rep["totals"]["points"]), "median_mm": a.get("median_mm"), "p95_mm": a.get("p95_mm"),
            "rms_mm": a.get("rms_mm"), "frac_over_1mm": a.get("frac_over_1mm"), "coverage": a.get("coverage_mean"),
            "seconds": dt, "eval": ev}


def _complete(folder: Path, views: int) -> bool:
    """A complete scan of ``views`` views is already there (kept by an earlier --out run)."""
    from ringscan.pipeline.formats.errors import FormatError
    from ringscan.pipeline.formats.scan import load_scan

    try:
        return (folder / "scan.json").is_file() and len(load_scan(folder).views) == views
    except FormatError:
        return False


def compare(work: Path, *, views: int, scene: str, small: bool, device, seed: int = 1, live: bool = False) -> dict:
    """Simulate, capture, reconstruct and measure both; returns both figure sets."""
    from ringscan.pipeline.formats.rig import default_rig
    from ringscan.pipeline.simulate.scan import simulate_scan

    rig = small_rig() if small else default_rig()
    patterns = patterns_for(small)
    sim = work / "simulated"
    cap = work / "captured"
    t_sim = t_cap = 0.0
    if not _complete(sim, views):
        t0 = time.perf_counter()
        simulate_scan(sim, scene=scene, rig=rig, patterns=patterns, views=views, device=device, progress=False)
        t_sim = time.perf_counter() - t0
    if not _complete(cap, views):
        t0 = time.perf_counter()
        capture_emulated(cap, rig, patterns, scene, views, seed=seed, device=device)
        t_cap = time.perf_counter() - t0
    out = {"simulated": measure(sim, sim, work / "recon_sim", device),
           "captured": measure(cap, sim, work / "recon_cap", device)}
    out["simulated"]["make_s"], out["captured"]["make_s"] = t_sim, t_cap
    if live:
        from ringscan.pipeline.reconstruct.live import LiveReconstructor

        if t_cap == 0.0:
            raise SystemExit("--live needs the captured scan made in this run (use a fresh --out)")
        rec = LiveReconstructor(work / "recon_live", device=device)
        t0 = time.perf_counter()
        scan = capture_emulated(work / "captured_live", rig, patterns, scene, views, seed=seed, device=device,
                                on_view=rec)
        rep = rec.finish(scan)
        out["live"] = {"seconds": time.perf_counter() - t0, "points": int(rep["totals"]["points"]),
                       "sequential_s": t_cap + out["captured"]["seconds"]}
    return out


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--views", type=int, default=8)
    p.add_argument("--scene", default="terrain")
    p.add_argument("--small", action="store_true", help="320x256 camera, 12-frame set")
    p.add_argument("--device", default=None)
    p.add_argument("--live", action="store_true", help="also time a capture that reconstructs while capturing")
    p.add_argument("--out", default=None,
                   help="keep the scans here; complete scans already there are reused (default: a temporary folder)")
    args = p.parse_args(argv)
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(args.out) if args.out else Path(tmp)
        res = compare(work, views=args.views, scene=args.scene, small=args.small, device=args.device, live=args.live)
    fmt = "{:<10} {:>9} {:>10} {:>8} {:>8} {:>9} {:>8} {:>8}"
    print(fmt.format("scan", "points", "median_mm", "p95_mm", "rms_mm", "coverage", "make_s", "recon_s"))
    for k in ("simulated", "captured"):
        r = res[k]
        print(fmt.format(k, r["points"], f"{r['median_mm']:.4f}", f"{r['p95_mm']:.4f}", f"{r['rms_mm']:.4f}",
                         f"{r['coverage']:.3f}", f"{r['make_s']:.1f}", f"{r['seconds']:.1f}"))
    s, c = res["simulated"], res["captured"]
    print(f"captured / simulated: points {c['points'] / max(s['points'], 1):.4f}, median "
          f"{c['median_mm'] / s['median_mm']:.3f}, p95 {c['p95_mm'] / s['p95_mm']:.3f}, coverage "
          f"{c['coverage'] / s['coverage']:.4f}")
    if "live" in res:
        lv = res["live"]
        print(f"capture then reconstruct: {lv['sequential_s']:.1f} s; reconstruct while capturing: "
              f"{lv['seconds']:.1f} s (ratio {lv['sequential_s'] / lv['seconds']:.2f}x); points "
              f"{lv['points']} vs {c['points']}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
