"""ringscan's two gray-rings decode kernels on the same frames: the eight-pixel-word kernel
(``decode_gray_rings_swar_kernel``: 8-bit frames, width a multiple of 8, up to 15 bits) against the
one-pixel-a-thread kernel (``decode_gray_rings_kernel``: every other case), one CPU thread, the
default rig's view size and codec (1280x1024, 7 bits, 6 sector bits). Prints each kernel's least
time over the rounds (interleaved, so the machine's load falls on both alike), their ratio, and
whether their outputs are the same bytes.

    python benchmarks/decode_kernels.py [--rounds 7]

Exit 1 when the outputs differ (the word kernel must be an exact twin)."""

from __future__ import annotations

import argparse
import sys
import time

import numpy as np
import warp as wp

from ringscan.kernels import init_warp, ring_labels
from ringscan.kernels.launch import set_cpu_threads
from ringscan.pipeline.codecs.render import render_frame
from ringscan.pipeline.formats.patterns import frame_names, parse_patterns


def frames_of_a_view(width: int, height: int) -> np.ndarray:
    """Every frame of the default gray-rings codec, blurred and scaled as a camera would see them: the
    projector's frames resized to the camera, a gain, an offset and noise (a decode's worth of real bits,
    weak ones at the band edges included)."""
    import cv2

    spec = parse_patterns({"codec": "gray-rings", "width": 1024, "height": 768, "center": [511.5, 383.5],
                           "rho0": 8.0, "pitch": 4.0, "bits": 7, "sector_bits": 6, "angle_steps": 0})
    rng = np.random.default_rng(0)
    out = []
    for name in frame_names(spec):
        f = cv2.resize(render_frame(spec, name), (width, height), interpolation=cv2.INTER_LINEAR)
        f = cv2.GaussianBlur(f.astype(np.float32), (0, 0), 1.0) * 0.7 + 20 + rng.normal(0, 2, f.shape)
        out.append(np.clip(np.rint(f), 0, 255).astype(np.uint8))
    return np.stack(out), spec


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rounds", type=int, default=7)
    args = ap.parse_args(argv)
    init_warp()
    set_cpu_threads(1)
    stack, spec = frames_of_a_view(1280, 1024)
    frames = wp.array(stack, dtype=wp.uint8, device="cpu")
    words = ring_labels.as_words

    def decode(word_kernel: bool):
        ring_labels.as_words = words if word_kernel else (lambda f: None)
        try:
            t = time.perf_counter()
            out = ring_labels.decode_gray_rings(frames, bits=spec.bits, sector_bits=spec.sector_bits, threads=1)
            return time.perf_counter() - t, out
        finally:
            ring_labels.as_words = words

    decode(True), decode(False)  # compile or load both kernels first
    best = {True: np.inf, False: np.inf}
    for _ in range(args.rounds):
        for kind in (True, False):
            dt, out = decode(kind)
            best[kind] = min(best[kind], dt)
    a, b = decode(True)[1], decode(False)[1]
    same = all(np.array_equal(getattr(a, k).numpy(), getattr(b, k).numpy())
               for k in ("code", "weak", "band", "sector", "contrast"))
    print(f"1280x1024, {stack.shape[0]} frames, one thread, least of {args.rounds} rounds:")
    print(f"  one pixel a thread (decode_gray_rings_kernel):      {best[False] * 1e3:7.1f} ms")
    print(f"  eight-pixel words (decode_gray_rings_swar_kernel): {best[True] * 1e3:7.1f} ms")
    print(f"  ratio {best[False] / best[True]:.2f}x; outputs {'the same bytes' if same else 'DIFFER'}")
    return 0 if same else 1


if __name__ == "__main__":
    sys.exit(main())
