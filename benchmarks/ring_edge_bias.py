"""Ring-edge radius bias of gray-rings samples against the virtual rig's truth,
binned by rho, with and without ``SampleSettings.ring_curvature``.

The scan: camera 1 of the two-camera test rig (320x256, the default rig's
1024x768 projector, bits 5, pitch 16, rho0 8, 6 sector bits, angle code), 80 mm
sphere. Each sample's true projector radius is the truth depth's projector
coordinate (bilinear at the sample's camera position); the truth and the
reconstruction share the rig's geometry code. Prints median(rho - rho_true)
per rho bin (projector px; > 0: rho reads too large).

    python benchmarks/ring_edge_bias.py [--seed N]
    python benchmarks/ring_edge_bias.py --scan S   # any simulated gray-rings scan (truth/), its first view
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import tempfile
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seed", type=int, default=0, help="rendering seed of the two-camera test rig's scan")
    ap.add_argument("--scan", default=None, help="a simulated gray-rings scan folder instead (e.g. ringscan "
                    "simulate --scene .../odedstein_spot.obj --out S)")
    args = ap.parse_args()
    import warp as wp

    from ringscan.kernels.ring_labels import decode_gray_rings
    from ringscan.kernels.ring_sampling import sample_gray_rings
    from ringscan.kernels.settings import SampleSettings
    from ringscan.pipeline.formats.patterns import parse_patterns
    from ringscan.pipeline.formats.scan import load_scan, read_view_frames
    from ringscan.pipeline.simulate.scan import simulate_scan
    from ringscan.pipeline.simulate.truth import load_truth
    from ringscan.pipeline.simulate.virtual_rig import RenderSettings
    from tests.support.two_camera_scan import ANGLE_PATTERNS, _decoded_maps, two_camera_rig

    wp.config.quiet = True
    with tempfile.TemporaryDirectory() as tmp:
        if args.scan:
            scan = load_scan(args.scan)
            rig, spec = scan.rig, scan.patterns
            label = args.scan
        else:
            rig = dataclasses.replace(two_camera_rig(), camera2=None)
            spec = parse_patterns(ANGLE_PATTERNS)
            scan = simulate_scan(Path(tmp) / "s", scene="sphere", rig=rig, patterns=spec, progress=False,
                                 settings=RenderSettings(seed=args.seed))
            label = f"two-camera test rig's camera 1, 80 mm sphere, seed {args.seed}"
        view = scan.views[0]
        frames = wp.array(read_view_frames(scan, view), device="cpu")
        t = load_truth(scan)
        pu, pv = _decoded_maps(rig, t.depth(view.name), t.lit(view.name), integer=False)
    lab = decode_gray_rings(frames, bits=spec.bits, sector_bits=spec.sector_bits)
    edges = [0, 25, 50, 100, 200, 300, 500, 1000]
    print(f"{label}: median rho - rho_true (projector px) per rho bin")
    print("rho bin      " + "  ".join(f"{a:>4d}-{b:<4d}" for a, b in zip(edges[:-1], edges[1:])))
    for on in (False, True):
        s = sample_gray_rings(frames, lab, bits=spec.bits, rho0=spec.rho0, pitch=spec.pitch,
                              settings=SampleSettings(ring_curvature=on)).numpy()
        u, v = s["uv"][:, 0], s["uv"][:, 1]
        x0, y0 = np.floor(u).astype(int), np.floor(v).astype(int)
        ok = (x0 >= 0) & (y0 >= 0) & (x0 < pu.shape[1] - 1) & (y0 < pu.shape[0] - 1)
        x0, y0, fx, fy = x0[ok], y0[ok], (u - np.floor(u))[ok], (v - np.floor(v))[ok]

        def bil(m):
            return ((1 - fx) * (1 - fy) * m[y0, x0] + fx * (1 - fy) * m[y0, x0 + 1]
                    + (1 - fx) * fy * m[y0 + 1, x0] + fx * fy * m[y0 + 1, x0 + 1])

        r_true = np.hypot(bil(pu) - spec.center[0], bil(pv) - spec.center[1])
        err = s["rho"][ok] - r_true
        fin = np.isfinite(err) & (np.abs(err) < spec.pitch / 2)
        cells = []
        for a, b in zip(edges[:-1], edges[1:]):
            m = fin & (r_true >= a) & (r_true < b)
            cells.append(f"{np.median(err[m]):+9.3f}" if m.sum() >= 20 else "        -")
        print(f"{'corrected' if on else 'nominal':<12s} " + "  ".join(cells) + f"   (n {fin.sum()})")
        if not on:
            counts = [int((fin & (r_true >= a) & (r_true < b)).sum()) for a, b in zip(edges[:-1], edges[1:])]
            print(f"{'samples':<12s} " + "  ".join(f"{c:>9d}" for c in counts))


if __name__ == "__main__":
    main()
