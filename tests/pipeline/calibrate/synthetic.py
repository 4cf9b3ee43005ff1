"""Synthetic Gray-code captures with a known camera -> projector map (test helper)."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from ringscan.pipeline.calibrate.graycode import graycode_bits


def affine_map(w: int, h: int):
    """Projector (u, v) at camera pixel centres (x, y): an affine map, 0.55 projector px per camera px."""
    y, x = np.mgrid[0:h, 0:w].astype(np.float64)
    return 5.3 + 0.55 * x + 0.05 * y, 4.1 + 0.02 * x + 0.56 * y


def write_capture(folder: Path, *, cam=(160, 120), projector=(128, 96), wb_first=False, noise=1.0, seed=0,
                  gamma=1.0, levels=(20.0, 220.0)) -> tuple[np.ndarray, np.ndarray]:
    """Write graycode_NN.png frames of the affine scene; returns the true (u, v) maps.

    Each camera pixel averages 4x4 sub-samples of the projected binary pattern
    (pixel centres at integers: projector pixel k covers [k - 0.5, k + 0.5)).
    """
    rng = np.random.default_rng(seed)
    w, h = cam
    ss = 4
    off = (np.arange(ss) + 0.5) / ss - 0.5
    ys, xs = np.mgrid[0:h, 0:w].astype(np.float64)
    X = (xs[..., None, None] + off[None, None, None, :])
    Y = (ys[..., None, None] + off[None, None, :, None])
    U = 5.3 + 0.55 * X + 0.05 * Y
    V = 4.1 + 0.02 * X + 0.56 * Y
    col = np.floor(U + 0.5).astype(np.int64)
    row = np.floor(V + 0.5).astype(np.int64)
    cb, rb = graycode_bits(projector)
    lo, hi = levels

    def shot(lit):
        val = lit.mean(axis=(-1, -2))
        img = lo + (hi - lo) * val ** (1.0 / gamma) + rng.normal(0, noise, val.shape)
        return np.clip(np.round(img), 0, 255).astype(np.uint8)

    frames = []
    gc, gr = col ^ (col >> 1), row ^ (row >> 1)
    for bits, g in ((cb, gc), (rb, gr)):
        for j in range(bits):
            b = ((g >> (bits - 1 - j)) & 1).astype(np.float64)
            frames += [shot(b), shot(1 - b)]
    white, black = shot(np.ones_like(U)), shot(np.zeros_like(U))
    frames = [white, black] + frames if wb_first else frames + [white, black]
    folder.mkdir(parents=True, exist_ok=True)
    for i, f in enumerate(frames):
        cv2.imwrite(str(folder / f"graycode_{i:02d}.png"), f)
    return affine_map(w, h)
