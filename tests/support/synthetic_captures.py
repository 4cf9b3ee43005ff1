"""Synthetic Gray-code captures with a known camera -> projector map (test helper)."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from ringscan.pipeline.calibrate.graycode import graycode_bits


def affine_map(w: int, h: int, slope: float = 1.0):
    """Projector (u, v) at camera pixel centres (x, y): an affine map, 0.55 projector px per camera px (times
    ``slope``)."""
    y, x = np.mgrid[0:h, 0:w].astype(np.float64)
    return 5.3 + slope * (0.55 * x + 0.05 * y), 4.1 + slope * (0.02 * x + 0.56 * y)


SMALL_PROJECTOR = (128, 96)
"""The projector size (width, height) of :func:`write_capture` by default."""


def write_capture(folder: Path, *, cam=(160, 120), projector=SMALL_PROJECTOR, wb_first=False, noise=1.0, seed=0,
                  gamma=1.0, levels=(20.0, 220.0), blur_px=0.0, slope=1.0) -> tuple[np.ndarray, np.ndarray]:
    """Write graycode_NN.png frames of the affine scene; returns the true (u, v) maps.

    Each camera pixel averages 4x4 sub-samples of the projected binary pattern
    (pixel centres at integers: projector pixel k covers [k - 0.5, k + 0.5)); ``slope`` > 1: a camera pixel
    spans 0.55 x slope projector px, and averages as many more sub-samples (4 a projector px at least).
    ``blur_px``: a defocused projector, a Gaussian of this standard deviation in projector pixels
    (the pattern drawn 8 times finer, blurred, and looked up bilinearly at each sub-sample).
    """
    rng = np.random.default_rng(seed)
    w, h = cam
    ss = max(4, int(np.ceil(4 * 0.56 * slope)))
    off = (np.arange(ss) + 0.5) / ss - 0.5
    ys, xs = np.mgrid[0:h, 0:w].astype(np.float64)
    X = (xs[..., None, None] + off[None, None, None, :])
    Y = (ys[..., None, None] + off[None, None, :, None])
    U = 5.3 + slope * (0.55 * X + 0.05 * Y)
    V = 4.1 + slope * (0.02 * X + 0.56 * Y)
    col = np.floor(U + 0.5).astype(np.int64)
    row = np.floor(V + 0.5).astype(np.int64)
    cb, rb = graycode_bits(projector)
    lo, hi = levels

    def blurred(g, bits, j):
        """Bit j of codes g as the defocused projector shows it at every sub-sample (U or V's axis)."""
        n = (projector[0] if g is gc else projector[1]) + 8
        x = (np.arange(8 * n) + 0.5) / 8 - 0.5  # projector coordinate of each fine sample
        k = np.floor(x + 0.5).astype(np.int64)
        line = (((k ^ (k >> 1)) >> (bits - 1 - j)) & 1).astype(np.float32)[None, :]
        line = cv2.GaussianBlur(line, (0, 0), sigmaX=8 * blur_px, sigmaY=1e-3, borderType=cv2.BORDER_REPLICATE)[0]
        return np.interp(U if g is gc else V, x, line)

    def shot(lit):
        val = lit.mean(axis=(-1, -2))
        img = lo + (hi - lo) * val ** (1.0 / gamma) + rng.normal(0, noise, val.shape)
        return np.clip(np.round(img), 0, 255).astype(np.uint8)

    frames = []
    gc, gr = col ^ (col >> 1), row ^ (row >> 1)
    for bits, g in ((cb, gc), (rb, gr)):
        for j in range(bits):
            b = blurred(g, bits, j) if blur_px > 0 else ((g >> (bits - 1 - j)) & 1).astype(np.float64)
            frames += [shot(b), shot(1 - b)]
    white, black = shot(np.ones_like(U)), shot(np.zeros_like(U))
    frames = [white, black] + frames if wb_first else frames + [white, black]
    folder.mkdir(parents=True, exist_ok=True)
    for i, f in enumerate(frames):
        cv2.imwrite(str(folder / f"graycode_{i:02d}.png"), f)
    return affine_map(w, h, slope)


def point_toward(px, z, K, dist):
    """The camera-frame point at depth z that a camera (K, OpenCV distortion) shows at pixel px
    (bisection along the ray through px's direction: for lenses whose radial map rises)."""
    d = (np.asarray(px, float) - K[:2, 2]) / K[0, 0]
    lo, hi = 0.0, 10.0
    for _ in range(60):
        m = (lo + hi) / 2
        p, _ = cv2.projectPoints(np.array([[*(d * m), 1.0]]), np.zeros(3), np.zeros(3), K, dist)
        lo, hi = (m, hi) if np.linalg.norm(p.ravel() - K[:2, 2]) < np.linalg.norm(d * K[0, 0]) else (lo, m)
    return np.array([*(d * lo * z), z])


def render_charuco(board, *, K, dist, size, rvec, tvec, sq_px=50, supersample=3, noise=1.0, seed=0) -> np.ndarray:
    """A (H, W) uint8 image of a ChArUco ``board`` (``ringscan.pipeline.calibrate.board.Board``) at pose
    (rvec, tvec) seen by a camera whose distortion is radial only (k1, k2, 0, 0, k3[, k4, k5, k6]):
    each pixel's ray is found by inverting the radial map (a table), met with the board's plane and
    the board drawn by cv2.aruco looked up there; ``supersample`` x ``supersample`` samples a pixel."""
    d = np.concatenate([np.asarray(dist, float).ravel(), np.zeros(8)])[:8]
    if np.any(d[2:4]):
        raise ValueError("render_charuco: radial distortion only (p1 = p2 = 0)")
    aruco = cv2.aruco
    cb = aruco.CharucoBoard((board.cols + 1, board.rows + 1), board.square, board.marker or 0.75 * board.square,
                            aruco.getPredefinedDictionary(getattr(aruco, board.charuco)))
    margin = sq_px
    art = cb.generateImage(((board.cols + 1) * sq_px + 2 * margin, (board.rows + 1) * sq_px + 2 * margin),
                           marginSize=margin)
    w, h = size
    s = supersample
    ys, xs = np.mgrid[0:h * s, 0:w * s].astype(np.float64)
    u, v = (xs + 0.5) / s - 0.5, (ys + 0.5) / s - 0.5
    xd, yd = (u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1]
    r = np.linspace(0.0, 5.0, 50001)
    r2 = r * r
    rd = r * (1 + r2 * (d[0] + r2 * (d[1] + r2 * d[4]))) / (1 + r2 * (d[5] + r2 * (d[6] + r2 * d[7])))
    top = int(np.argmax(np.diff(rd) <= 0)) if np.any(np.diff(rd) <= 0) else len(r) - 1
    rad = np.hypot(xd, yd)
    scale = np.where(rad > 0, np.interp(rad, rd[:top + 1], r[:top + 1]) / np.maximum(rad, 1e-12), 1.0)
    R = cv2.Rodrigues(np.asarray(rvec, float))[0]
    Hinv = np.linalg.inv(np.column_stack([R[:, 0], R[:, 1], np.asarray(tvec, float).ravel()]))
    rays = np.stack([xd * scale, yd * scale, np.ones_like(xd)], -1) @ Hinv.T
    X, Y = rays[..., 0] / rays[..., 2], rays[..., 1] / rays[..., 2]
    # board (X, Y) mm -> the drawing's pixels: inner corner (i, j) at margin + (i + 1) sq_px - 0.5
    mx = (margin + (X / board.square + 1) * sq_px - 0.5).astype(np.float32)
    my = (margin + (Y / board.square + 1) * sq_px - 0.5).astype(np.float32)
    behind = (rays[..., 2] <= 0) | (rad > rd[top])
    mx[behind] = -1e4
    hi_res = cv2.remap(art, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=128)
    img = cv2.resize(hi_res.astype(np.float32), (w, h), interpolation=cv2.INTER_AREA)
    img = 30 + img * (200 / 255) + np.random.default_rng(seed).normal(0, noise, img.shape)
    return np.clip(np.round(img), 0, 255).astype(np.uint8)
