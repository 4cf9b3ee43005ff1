"""The ``decoded`` codec: imported captures whose every camera pixel already carries a
decoded projector position (``ringscan import``, docs/formats.md).

Frames ``proj_u``, ``proj_v`` (16-bit fixed point: value = round((coordinate + 1) *
``scale``), 0 = not decoded; ``scale`` is scan.json's ``patterns.scale``, ``DECODED_SCALE`` = 32 up to a
2047 px projector) and ``contrast`` (white - black, 16-bit).
Each decoded pixel becomes one sample that keeps both projector coordinates: rho =
|p - c| around the pattern centre c (the projector's principal point) and the polar
angle phi = atan2(v_p - c_v, u_p - c_u), each with a predicted standard deviation,
so the triangulation fits the full projector pixel (the camera ray against the
projector ray, through the projector's lens); with ``--constraint rings`` it meets
the cone of its own rho and picks the root by the angle's sector (docs/design.md §3, §4).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass

import numpy as np
import warp as wp

from ringscan.kernels.decoded_maps import DecodedMapParams, decoded_map_samples
from ringscan.kernels.samples import Samples
from ringscan.pipeline.codecs.shading import sample_shading
from ringscan.pipeline.codecs.base import Codec, StageSettings
from ringscan.pipeline.formats.patterns import DECODED_SCALE, PATTERN_LAYOUTS, PatternSpec
from ringscan.pipeline.formats.scan import Scan

__all__ = ["NAME", "DecodedCodec", "DecodedSettings", "extract_decoded", "decoded_samples", "CONTRAST_FULL"]

NAME = "decoded"
"""The codec's name (scan.json ``patterns.codec``): what code outside the codec spells it by."""

CONTRAST_FULL = 64.0
"""White - black (8-bit levels) at which a sample's confidence reaches 1."""
SIGMA_SUBPIXEL_PX = 0.05
"""Standard deviation (projector px) of a sub-pixel coordinate at ``CONTRAST_FULL``;
it grows as 1 / contrast (the crossing of a pattern and its inverse moves by
noise / slope), with the fixed-point step of the frames as its floor. What the
calibration adds on a real rig is measured per view by the triangulation
(``reconstruct.view``: the calibration floor)."""
SIGMA_INTEGER_PX = 1.0 / math.sqrt(12.0)
"""Standard deviation of an integer code (a uniform error over one projector pixel)."""


def coordinate_sigma(x: np.ndarray, contrast: np.ndarray, scale: int = DECODED_SCALE) -> np.ndarray:
    """Predicted standard deviation (projector px) of decoded coordinates ``x`` (read from maps of ``scale``
    steps a px): integer codes (the importer's fallback, or ``--integer``) are uniform over a
    pixel; sub-pixel ones follow the contrast."""
    integer = np.abs(x - np.round(x)) < 0.5 / scale
    floor = 1.0 / (scale * math.sqrt(12.0))
    sub = np.maximum(SIGMA_SUBPIXEL_PX * CONTRAST_FULL / np.maximum(contrast, 1.0), floor)
    return np.where(integer, SIGMA_INTEGER_PX, sub)


def decoded_samples(u: np.ndarray, v: np.ndarray, contrast: np.ndarray, *, center, sector_bits: int,
                    scale: int = DECODED_SCALE) -> dict:
    """NumPy samples of decoded maps.

    ``u``, ``v``: (H, W) float projector coordinates, NaN where not decoded;
    ``contrast``: (H, W) white - black in 8-bit levels.

    Returns:
        dict of (n,) arrays: ``uv`` (n, 2) float32 camera pixel, ``rho`` float32,
        ``phi`` float32 polar angle (rad), ``sector`` int32, ``confidence``
        float32, ``pixel`` int32, ``sigma_rho`` and ``sigma_tan`` float32 (projector
        px: the u and v errors turned into the radial and tangential directions), ``shading``
        float32 (the contrast's relative gradient per camera px: ``shading.sample_shading``).
    """
    u = np.asarray(u, np.float64)
    v = np.asarray(v, np.float64)
    if u.ndim != 2 or u.shape != v.shape or np.shape(contrast) != u.shape:
        raise ValueError(f"decoded_samples: u, v, contrast must be (H, W) of one shape, got {u.shape}, {v.shape}, "
                         f"{np.shape(contrast)}")
    ok = np.isfinite(u) & np.isfinite(v)
    pix = np.flatnonzero(ok.ravel()).astype(np.int32)
    con = np.asarray(contrast, np.float64).ravel()[pix]
    out = _samples_at(pix, u.ravel()[pix], v.ravel()[pix], con, u.shape[1], center=center, sector_bits=sector_bits,
                      scale=scale, rates=(map_rate(u).ravel()[pix], map_rate(v).ravel()[pix]))
    out["shading"] = sample_shading(np.asarray(contrast, np.float64), out["uv"])
    return out


def map_rate(a: np.ndarray) -> np.ndarray:
    """(H, W) projector px per camera px of a decoded map ``a`` (NaN: not decoded) at each pixel: the norm of
    its steps across and down, each the smaller of the two sides' |change| to a decoded neighbour (a depth edge
    on one side is not the map's slope), the one side where the other is not decoded, 0 where neither is."""
    def step(axis):
        pad = np.pad(a, [(1, 1) if k == axis else (0, 0) for k in (0, 1)], constant_values=np.nan)
        sl = lambda k: tuple(slice(1 + k, pad.shape[i] - 1 + k) if i == axis else slice(None) for i in (0, 1))  # noqa: E731
        fwd, back = np.abs(pad[sl(1)] - a), np.abs(a - pad[sl(-1)])
        both = np.fmin(fwd, back)  # (NaN where a side is not decoded: fmin takes the other)
        return np.where(np.isnan(both), 0.0, both)
    gx, gy = step(1), step(0)
    return np.sqrt(gx * gx + gy * gy)


def _samples_at(pix: np.ndarray, up: np.ndarray, vp: np.ndarray, con: np.ndarray, W: int, *, center,
                sector_bits: int, scale: int = DECODED_SCALE, rates: tuple | None = None) -> dict:
    """:func:`decoded_samples` of the decoded pixels ``pix`` (linear indices in an image ``W`` wide), their
    float64 coordinates ``up``, ``vp`` and contrast ``con`` (8-bit levels)."""
    uv = np.stack([pix % W, pix // W], 1).astype(np.float32)
    du = up - center[0]
    dv = vp - center[1]
    rho = np.hypot(du, dv)
    phi = np.arctan2(dv, du)
    if sector_bits > 0:
        n = 2 ** sector_bits
        sector = np.clip(np.floor((phi + np.pi) / (2 * np.pi) * n), 0, n - 1).astype(np.int32)
    else:
        sector = np.full(pix.size, -1, np.int32)
    conf = np.clip(con / CONTRAST_FULL, 0.0, 1.0).astype(np.float32)
    su, sv = coordinate_sigma(up, con, scale), coordinate_sigma(vp, con, scale)
    if rates is not None:  # where a camera px spans more than one projector px, a crossing's error as many more
        for s_, x, r in ((su, up, rates[0]), (sv, vp, rates[1])):
            sub = np.abs(x - np.round(x)) >= 0.5 / scale  # (coordinate_sigma's integer codes keep theirs)
            s_[sub] *= np.maximum(r[sub], 1.0)
    su2, sv2 = su ** 2, sv ** 2
    c2, s2 = np.cos(phi) ** 2, np.sin(phi) ** 2
    return {"uv": uv, "rho": rho.astype(np.float32), "phi": phi.astype(np.float32), "sector": sector,
            "confidence": conf, "pixel": pix,
            "sigma_rho": np.sqrt(su2 * c2 + sv2 * s2).astype(np.float32),
            "sigma_tan": np.sqrt(su2 * s2 + sv2 * c2).astype(np.float32)}


def _map_params(spec: PatternSpec, light_gradient: bool = True) -> DecodedMapParams:
    """The kernel's reading of this codec's maps (:func:`decoded_samples`'s constants; ``light_gradient``: each
    sample's ``shading`` too)."""
    p = DecodedMapParams()
    p.light_gradient = 1 if light_gradient else 0
    p.scale = float(spec.scale)
    p.contrast_scale = 257.0
    p.center = wp.vec2d(float(spec.center[0]), float(spec.center[1]))
    p.sectors = 2 ** int(spec.sector_bits) if spec.sector_bits > 0 else 0
    p.contrast_full = CONTRAST_FULL
    p.sigma_subpixel = SIGMA_SUBPIXEL_PX
    p.sigma_integer = SIGMA_INTEGER_PX
    return p


@dataclass(frozen=True)
class DecodedSettings:
    """Settings of the ``decoded`` codec: none (the captures were decoded on import)."""


def extract_decoded(frames: wp.array, scan: Scan, settings: DecodedSettings, threads: int, *,
                    light_gradient: bool = True) -> tuple[Samples, dict]:
    """Decode + sampling stage of the ``decoded`` codec (:class:`DecodedCodec`).

    Args:
        frames: (3, H, W) uint16 Warp array: proj_u, proj_v, contrast.
        light_gradient: each sample's ``shading`` too (False: None, for matching, which reads none).

    Returns:
        (Samples, stats) with ``pixels_decoded`` and ``times_s``.
    """
    spec = scan.patterns
    if spec.codec != "decoded":
        raise ValueError(f"extract_decoded: the scan's codec is {spec.codec!r}, not decoded")
    t0 = time.perf_counter()
    if frames.ndim != 3 or frames.shape[0] != 3 or frames.dtype != wp.uint16:
        raise ValueError(f"extract_decoded: expected (3, H, W) uint16 frames, got {frames.shape} {frames.dtype}")
    # on the frames' device: count, scan, write (kernels.decoded_maps); decoded_samples is its NumPy statement
    smp = decoded_map_samples(frames, params=_map_params(spec, light_gradient), threads=threads)
    stats = {"pixels_decoded": len(smp), "samples": len(smp),
             "times_s": {"decode": time.perf_counter() - t0}}
    return smp, stats


class DecodedCodec(Codec[DecodedSettings]):
    """Imported captures (``ringscan import``): frames ``proj_u``, ``proj_v``,
    ``contrast``; one sample per decoded pixel. Not projectable."""

    layout = PATTERN_LAYOUTS[NAME]
    settings_type = DecodedSettings

    @property
    def isotropic_code_error(self) -> bool:
        return True  # u's and v's sigmas alike: the radius's and the angle's are turns of them

    def full_coordinate(self, spec: PatternSpec) -> bool:
        return True  # every sample is a decoded (u_p, v_p)

    def settings_from(self, stages: StageSettings) -> DecodedSettings:
        return DecodedSettings()

    def extract(self, frames: wp.array, scan: Scan, settings: DecodedSettings, *,
                threads: int) -> tuple[Samples, dict]:
        return extract_decoded(frames, scan, settings, threads)

    def extract_for_matching(self, frames: wp.array, scan: Scan, settings: DecodedSettings, *,
                             threads: int) -> tuple[Samples, dict]:
        # every pixel a sample: its light gradient is a sixth of the stage's time, and matching reads none
        return extract_decoded(frames, scan, settings, threads, light_gradient=False)
