"""The ``decoded`` codec: imported captures whose every camera pixel already carries a
decoded projector position (``ringscan import``, docs/formats.md).

Frames ``proj_u``, ``proj_v`` (16-bit fixed point: value = round((coordinate + 1) *
``DECODED_SCALE``), 0 = not decoded) and ``contrast`` (white - black, 16-bit).
Each decoded pixel becomes one sample: rho = |p - c| around the pattern centre c
(the projector's principal point) and the sector of its polar angle
atan2(v_p - c_v, u_p - c_u), so the triangulation meets the camera ray with the
cone of its own rho and picks the root by the angle (DESIGN §3, §4).
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
import warp as wp

from ringscan.kernels.samples import Samples
from ringscan.pipeline.codecs.base import Codec, StageSettings
from ringscan.pipeline.formats.patterns import DECODED_SCALE, PATTERN_LAYOUTS
from ringscan.pipeline.formats.scan import Scan

__all__ = ["DecodedCodec", "DecodedSettings", "extract_decoded", "decoded_samples", "CONTRAST_FULL"]

CONTRAST_FULL = 64.0
"""White - black (8-bit levels) at which a sample's confidence reaches 1."""


def decoded_samples(u: np.ndarray, v: np.ndarray, contrast: np.ndarray, *, center, sector_bits: int):
    """NumPy samples of decoded maps: (uv (n, 2), rho (n,), sector (n,), confidence (n,), pixel (n,)).

    ``u``, ``v``: (H, W) float projector coordinates, NaN where not decoded;
    ``contrast``: (H, W) white - black in 8-bit levels.
    """
    u = np.asarray(u, np.float64)
    v = np.asarray(v, np.float64)
    if u.ndim != 2 or u.shape != v.shape or np.shape(contrast) != u.shape:
        raise ValueError(f"decoded_samples: u, v, contrast must be (H, W) of one shape, got {u.shape}, {v.shape}, "
                         f"{np.shape(contrast)}")
    ok = np.isfinite(u) & np.isfinite(v)
    pix = np.flatnonzero(ok.ravel()).astype(np.int32)
    W = u.shape[1]
    uv = np.stack([pix % W, pix // W], 1).astype(np.float32)
    du = u.ravel()[pix] - center[0]
    dv = v.ravel()[pix] - center[1]
    rho = np.hypot(du, dv).astype(np.float32)
    if sector_bits > 0:
        n = 2 ** sector_bits
        phi = np.arctan2(dv, du)
        sector = np.clip(np.floor((phi + np.pi) / (2 * np.pi) * n), 0, n - 1).astype(np.int32)
    else:
        sector = np.full(pix.size, -1, np.int32)
    conf = np.clip(np.asarray(contrast, np.float64).ravel()[pix] / CONTRAST_FULL, 0.0, 1.0).astype(np.float32)
    return uv, rho, sector, conf, pix


@dataclass(frozen=True)
class DecodedSettings:
    """Settings of the ``decoded`` codec: none (the captures were decoded on import)."""


def extract_decoded(frames: wp.array, scan: Scan, settings: DecodedSettings, threads: int) -> tuple[Samples, dict]:
    """Decode + sampling stage of the ``decoded`` codec (:class:`DecodedCodec`).

    Args:
        frames: (3, H, W) uint16 Warp array: proj_u, proj_v, contrast.

    Returns:
        (Samples, stats) with ``pixels_decoded`` and ``times_s``.
    """
    spec = scan.patterns
    if spec.codec != "decoded":
        raise ValueError(f"extract_decoded: the scan's codec is {spec.codec!r}, not decoded")
    t0 = time.perf_counter()
    fr = frames.numpy()
    if fr.ndim != 3 or fr.shape[0] != 3 or fr.dtype != np.uint16:
        raise ValueError(f"extract_decoded: expected (3, H, W) uint16 frames, got {fr.shape} {fr.dtype}")
    good = (fr[0] > 0) & (fr[1] > 0)
    u = np.where(good, fr[0] / DECODED_SCALE - 1.0, np.nan)
    v = np.where(good, fr[1] / DECODED_SCALE - 1.0, np.nan)
    uv, rho, sector, conf, pix = decoded_samples(u, v, fr[2] / 257.0, center=spec.center,
                                                 sector_bits=spec.sector_bits)
    dev = frames.device
    smp = Samples(uv=wp.array(uv, dtype=wp.vec2, device=dev), rho=wp.array(rho, dtype=wp.float32, device=dev),
                  ring=None, sector=wp.array(sector, dtype=wp.int32, device=dev),
                  confidence=wp.array(conf, dtype=wp.float32, device=dev),
                  pixel=wp.array(pix, dtype=wp.int32, device=dev))
    stats = {"pixels_decoded": int(pix.size), "samples": int(pix.size),
             "times_s": {"decode": time.perf_counter() - t0}}
    return smp, stats


class DecodedCodec(Codec[DecodedSettings]):
    """Imported captures (``ringscan import``): frames ``proj_u``, ``proj_v``,
    ``contrast``; one sample per decoded pixel. Not projectable."""

    layout = PATTERN_LAYOUTS["decoded"]
    settings_type = DecodedSettings

    def settings_from(self, stages: StageSettings) -> DecodedSettings:
        return DecodedSettings()

    def extract(self, frames: wp.array, scan: Scan, settings: DecodedSettings, *,
                threads: int) -> tuple[Samples, dict]:
        return extract_decoded(frames, scan, settings, threads)
