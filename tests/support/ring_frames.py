"""Gray-rings frames drawn straight from the pattern (no camera): a small pattern set and its frame stack,
for the kernel tests of decode and sampling (test_ring_labels, test_ring_sampling, test_launch)."""

import cv2
import numpy as np

from ringscan.pipeline.codecs.render import render_frames
from ringscan.pipeline.formats.patterns import PatternSpec, frame_names


def gray_rings_spec(**kw):
    """A small gray-rings pattern set (160x120, 4 bits, 3 sector bits); ``kw`` replaces any field."""
    d = dict(codec="gray-rings", width=160, height=120, center=(79.5, 59.5), rho0=6.0, pitch=4.0, bits=4, sector_bits=3)
    d.update(kw)
    return PatternSpec(**d)


def frame_stack(spec, blur=0.0, dtype=np.uint8):
    """The frames of ``spec`` as a camera would see them, stacked: optionally blurred (Gaussian, ``blur`` px),
    rounded to ``dtype`` (16 bits: the 8-bit levels times 257)."""
    fr = render_frames(spec)
    imgs = []
    for n in frame_names(spec):
        f = fr[n].astype(np.float32)
        if blur:
            f = cv2.GaussianBlur(f, (0, 0), blur)
        if dtype == np.uint16:
            f = f * 257.0
        imgs.append(np.clip(np.rint(f), 0, np.iinfo(dtype).max).astype(dtype))
    return np.stack(imgs)
