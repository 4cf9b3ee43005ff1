"""Phase-rings frames of a flat target seen pixel for pixel (camera = projector grid) and their decode, for
the phase kernels' tests (tests/kernels/test_phase.py, test_launch.py)."""

import cv2
import numpy as np
import warp as wp

from ringscan.kernels.phase import decode_phase
from ringscan.kernels.response import response_tables
from ringscan.kernels.ring_labels import decode_gray_rings
from ringscan.kernels.settings import PhaseSettings
from ringscan.pipeline.codecs.render import render_frames
from ringscan.pipeline.formats.patterns import PatternSpec, frame_names

def phase_spec(**kw):
    """A small phase-rings pattern set (160x120, 4 bits, 2 sector bits, 4 steps); ``kw`` replaces any field."""
    d = dict(codec="phase-rings", width=160, height=120, center=(79.5, 59.5), rho0=4.0, pitch=6.0, bits=4,
             sector_bits=2, steps=4)
    d.update(kw)
    return PatternSpec(**d)


def phase_stack(spec, *, blur=0.6, cam_gamma=1.0, light_gamma=1.0, noise=0.0, seed=0, mix_with=None):
    """Camera frames of a flat albedo-0.8 target seen pixel for pixel: light response,
    projector blur, ambient 0.05, camera response, noise, 8-bit."""
    rng = np.random.default_rng(seed)
    fr = render_frames(spec)
    other = render_frames(mix_with) if mix_with is not None else None
    out = []
    for n in frame_names(spec):
        e = (fr[n].astype(np.float64) / 255.0) ** light_gamma
        if other is not None:
            e = 0.5 * e + 0.5 * (other[n].astype(np.float64) / 255.0) ** light_gamma
        if blur:
            e = cv2.GaussianBlur(e, (0, 0), blur)
        irr = 0.8 * (0.05 + e) / 0.85
        val = 255.0 * 0.9 * irr ** (1.0 / cam_gamma) + rng.normal(0.0, noise, irr.shape)
        out.append(np.clip(np.rint(val), 0, 255).astype(np.uint8))
    return np.stack(out)


def phase_decode(frames_np, spec, device, *, cam_gamma=1.0, light_gamma=1.0, settings=PhaseSettings(), weighted=True):
    """The gray-rings labels and the phase of ``frames_np`` on ``device``: (frames, labels, phase map)."""
    fr = wp.array(frames_np, device=device)
    lab = decode_gray_rings(fr, bits=spec.bits, sector_bits=spec.sector_bits)
    lut, wlut = response_tables(255, camera_gamma=cam_gamma, weighted=weighted)
    ph = decode_phase(fr, lab, bits=spec.bits, sector_bits=spec.sector_bits, steps=spec.steps,
                      lut=wp.array(lut, device=device), wlut=wp.array(wlut, device=device), light_gamma=light_gamma,
                      settings=settings)
    return fr, lab, ph
