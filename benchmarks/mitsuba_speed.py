"""How fast the Mitsuba renderer is, next to ringscan's own (``ringscan simulate --renderer mitsuba``).

Renders the default sphere on the default rig with its perspective projector (optionally at
1/K the camera's size, the same field of view) with each renderer and prints, per renderer:
the per-view set-up (Mitsuba: the scene, the ambient image and the truth's ray casts;
ringscan: the geometry pass), the median time of a frame, and the ratio of Mitsuba's frame
to ringscan's measured in the same run. Mitsuba's variant is chosen as
``ringscan simulate`` chooses it, or given with ``--variant``.

    python benchmarks/mitsuba_speed.py [--camera-scale K] [--frames N] [--variant scalar_rgb|llvm_ad_rgb]
                                       [--spp 4] [--supersample 2]
"""

from __future__ import annotations

import argparse
import sys
import time
from dataclasses import replace

import numpy as np

from ringscan.pipeline.codecs.render import render_frame
from ringscan.pipeline.formats.patterns import frame_names, parse_patterns
from ringscan.pipeline.formats.rig import default_rig
from ringscan.pipeline.simulate.mitsuba_render import MitsubaRig, MitsubaSettings
from ringscan.pipeline.simulate.virtual_rig import RenderSettings, VirtualRig

PATTERNS = {"codec": "gray-rings", "bits": 7, "pitch": 4, "rho0": 8, "sector_bits": 9, "width": 1024,
            "height": 768, "center": [511.5, 383.5]}


def scaled_camera(cam, k: int):
    K = cam.K.copy()
    K[:2, :2] /= k
    K[:2, 2] = (cam.K[:2, 2] + 0.5) / k - 0.5
    return replace(cam, width=cam.width // k, height=cam.height // k, K=K)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--camera-scale", type=int, default=1, metavar="K")
    ap.add_argument("--frames", type=int, default=3, help="frames timed per renderer (default 3)")
    ap.add_argument("--variant", default=None, help="Mitsuba variant (default: as simulate chooses)")
    ap.add_argument("--spp", type=int, default=MitsubaSettings().spp)
    ap.add_argument("--supersample", type=int, default=RenderSettings().supersample)
    args = ap.parse_args(argv)
    rig = default_rig(light_model="perspective")
    rig = replace(rig, camera=scaled_camera(rig.camera, args.camera_scale))
    spec = parse_patterns(PATTERNS)
    frames = [render_frame(spec, n) for n in frame_names(spec)[:args.frames]]
    settings = RenderSettings(supersample=args.supersample)
    c = rig.camera
    print(f"default sphere, perspective projector 1024x768, camera {c.width}x{c.height}, S = {args.supersample}")

    t0 = time.perf_counter()
    vr = VirtualRig(rig, "sphere", settings=settings, device="cpu")
    vr.render(frames[0], seed=0)  # compiles the kernels once
    vr.set_turntable(1.0)
    t1 = time.perf_counter()
    vr.geometry()
    warp_setup = time.perf_counter() - t1
    warp = []
    for i, f in enumerate(frames):
        t = time.perf_counter()
        vr.render(f, seed=i)
        warp.append(time.perf_counter() - t)
    print(f"ringscan (Warp, cpu): geometry pass {warp_setup:.2f} s, a frame {np.median(warp):.3f} s "
          f"(first use, kernels loaded: {t1 - t0:.1f} s)")

    ms = MitsubaSettings(spp=args.spp, variant=args.variant)
    t0 = time.perf_counter()
    mr = MitsubaRig(rig, "sphere", settings=settings, mitsuba=ms)
    t1 = time.perf_counter()
    mr.truth()
    t2 = time.perf_counter()
    mi = []
    for i, f in enumerate(frames):
        t = time.perf_counter()
        mr.render(f, seed=i)
        mi.append(time.perf_counter() - t)
    Wc, Hc = mr._canvas
    print(f"Mitsuba {mr.variant}: set-up {t1 - t0:.2f} s, scene + ambient image ({ms.ambient_spp} spp) + truth "
          f"{t2 - t1:.2f} s, a frame {np.median(mi):.2f} s (first {mi[0]:.2f} s; canvas {Wc}x{Hc}, {ms.spp} spp, "
          f"max_depth {ms.max_depth})")
    print(f"Mitsuba's frame / ringscan's frame: {np.median(mi) / np.median(warp):.0f}x")
    return 0


if __name__ == "__main__":
    sys.exit(main())
