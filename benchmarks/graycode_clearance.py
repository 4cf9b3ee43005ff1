"""Which bits of real Gray-code captures stand clear of the noise, and what trusting only those does.

For each capture of ../shared/data/procam (1024x768 projector, OpenCV's layout), decodes the
column code twice: trusting every bit (the decode before bit clearance: the thresholds at 0)
and trusting only the bits that stand clear (``graycode.bit_clearance``). Prints the measured
camera noise, the share of decoded pixels whose finest bits give way to coarser ones, those
left out as ``low_modulation``, and the local roughness of the projector column u (|u - the mean
of its two neighbours along the camera row|, projector px: a smooth surface gives ~0, a misread
bit a whole pixel or more) on each group of pixels, both ways.

    python benchmarks/graycode_clearance.py [--data ../shared/data/procam] [--captures capture_1 capture_2]
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

import ringscan.pipeline.calibrate.graycode as gc
from ringscan.pipeline.calibrate.capture_reader import read_capture

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "procam"


def roughness(dec, mask) -> str:
    u = np.where(dec.valid, dec.u, np.nan)
    r = np.abs(u[:, 1:-1] - 0.5 * (u[:, :-2] + u[:, 2:]))
    m = mask[:, 1:-1] & np.isfinite(r)
    if not m.any():
        return "no pixels"
    return f"median {np.median(r[m]):.3f} px, p90 {np.percentile(r[m], 90):.3f} px ({int(m.sum())} px)"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, default=DATA)
    ap.add_argument("--captures", nargs="+", default=["capture_1", "capture_2", "capture_3"])
    ap.add_argument("--projector", default="1024x768")
    args = ap.parse_args(argv)
    proj = tuple(int(x) for x in args.projector.split("x"))
    for name in args.captures:
        cap = read_capture(args.data / name, projector=proj)
        new = gc.subpixel_map(cap, gc.decode_graycode(cap))
        saved = gc.CLEAR_NOISE_SIGMAS, gc.CLEAR_CONTRAST_FRACTION
        gc.CLEAR_NOISE_SIGMAS = gc.CLEAR_CONTRAST_FRACTION = 0.0
        try:
            old = gc.subpixel_map(cap, gc.decode_graycode(cap))
        finally:
            gc.CLEAR_NOISE_SIGMAS, gc.CLEAR_CONTRAST_FRACTION = saved
        dropped = old.valid & ~new.valid
        coarse = new.valid & (new.coarse[..., 0] > 0)
        clear = new.valid & (new.coarse[..., 0] == 0)
        n = max(1, int(new.valid.sum()))
        print(f"{name}: noise {new.noise:.2f} levels; {int(new.valid.sum())} pixels decoded ({int(old.valid.sum())} "
              f"trusting every bit); column from coarser bits {100 * coarse.sum() / n:.1f} %, left out "
              f"(low_modulation) {int(new.low_modulation.sum())}")
        print(f"  left out, as every bit trusted gave them: {roughness(old, dropped)}")
        print(f"  from coarser bits: every bit trusted {roughness(old, coarse)}; now {roughness(new, coarse)}")
        print(f"  every bit clear: every bit trusted {roughness(old, clear)}; now {roughness(new, clear)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
