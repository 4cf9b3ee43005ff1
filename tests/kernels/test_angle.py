"""The angle code against frames drawn from its own formula: a camera that sees
the projector's grid one to one (known truth at every sub-pixel position)."""

import numpy as np
import pytest
import warp as wp

from ringscan.kernels.angle import ANGLE_STATUS_NAMES, decode_angle
from ringscan.kernels.settings import AngleSettings
from ringscan.pipeline.formats.patterns import angle_periods, angle_zones
from tests.support.angle_frames import (
    BANDS,
    PITCH,
    RHO0,
    SB,
    STEPS,
    C,
    angle_decode,
    angle_frames,
    angle_lut,
    angle_samples,
)

STATUS = {n: i for i, n in enumerate(ANGLE_STATUS_NAMES)}


def test_zones_double_and_respect_the_period_and_the_sector_code():
    starts, periods = angle_zones(rho0=RHO0, pitch=PITCH, bands=BANDS, sector_bits=SB, min_period_px=12.0)
    assert starts[0] == RHO0 and np.all(np.diff(starts) > 0)
    assert np.all(periods[1:] == 2 * periods[:-1]) and periods[-1] <= 2 ** (SB - 1)
    assert np.all(2 * np.pi * starts / periods >= 12.0 - 1e-6) | (periods == 1).all()
    # zone edges sit on band centres
    assert np.allclose(((starts[1:] - RHO0) / PITCH) % 1.0, 0.5)
    assert angle_periods([RHO0, starts[-1] + 1], starts, periods).tolist() == [periods[0], periods[-1]]
    with pytest.raises(ValueError):
        angle_zones(rho0=8, pitch=0, bands=4, sector_bits=6, min_period_px=12)


@pytest.mark.parametrize("gamma_cam", [1.0, 2.2])
def test_angle_comes_back_at_sub_pixel_positions(device, gamma_cam):
    zones = angle_zones(rho0=RHO0, pitch=PITCH, bands=BANDS, sector_bits=SB, min_period_px=12.0)
    frames, _, _ = angle_frames(gamma_cam=gamma_cam, zones=zones)
    pts, r, a, sector = angle_samples()
    A = angle_decode(device, frames, pts, r, sector, zones, angle_lut(gamma_cam))
    st = A.status.numpy()
    phi = A.phi.numpy()
    P = angle_periods(r, *zones)
    # away from zone edges (mixed fringes), every sample decodes
    edge = np.min(np.abs(r[:, None] - zones[0][None, 1:]), axis=1) < 1.5 if len(zones[0]) > 1 else np.zeros(len(r), bool)
    assert np.mean(st[~edge] == 0) > 0.99
    ok = (st == 0) & ~edge
    err_tan = np.abs(np.angle(np.exp(1j * (phi[ok] - a[ok])))) * r[ok]  # projector px along the ring
    # bilinear interpolation of a cosine at a period of >= 12 px: well below a tenth of a pixel
    assert np.percentile(err_tan, 99) < 0.15
    assert np.all(np.isnan(phi[st != 0]))
    assert set(np.unique(P)) >= {zones[1][0], zones[1][-1]}


def test_sigma_matches_the_scatter_and_sectors_unwrap(device):
    zones = angle_zones(rho0=RHO0, pitch=PITCH, bands=BANDS, sector_bits=SB, min_period_px=12.0)
    pts, r, a, sector = angle_samples(n=400, seed=3)
    errs, sig = [], []
    for seed in range(12):
        frames, _, _ = angle_frames(noise=2.0, seed=seed, zones=zones)
        A = angle_decode(device, frames, pts, r, sector, zones, angle_lut(1.0), AngleSettings(noise=2.0))
        errs.append(np.angle(np.exp(1j * (A.phi.numpy() - a))) * r)
        sig.append(A.sigma_tan.numpy())
    errs, sig = np.array(errs), np.array(sig)
    good = np.all(np.isfinite(errs), axis=0) & (np.min(np.abs(r[:, None] - zones[0][None, 1:]), axis=1) > 2)
    assert good.mean() > 0.9
    # no period slip: every error is a fraction of a period
    assert np.abs(errs[:, good]).max() < 0.25 * (2 * np.pi * r[good] / angle_periods(r[good], *zones)).min()
    ratio = errs[:, good].std(axis=0) / sig[:, good].mean(axis=0)
    # pixel noise at integer positions only: interpolation averages it, so the scatter is at or below the prediction
    assert 0.4 < np.median(ratio) < 1.2


def test_unknown_sector_dark_and_flat(device):
    zones = angle_zones(rho0=RHO0, pitch=PITCH, bands=BANDS, sector_bits=SB, min_period_px=12.0)
    frames, _, _ = angle_frames(zones=zones)
    pts, r, a, sector = angle_samples(n=200)
    far = r > zones[0][-1] + 2
    A = angle_decode(device, frames, pts, r, np.where(far, -1, sector), zones, angle_lut(1.0))
    st = A.status.numpy()
    assert np.all(st[far] == STATUS["no_sector"])
    flat = frames.copy()
    flat[2:] = flat[2:].mean(axis=0, keepdims=True).astype(np.uint8)
    status = angle_decode(device, flat, pts, r, sector, zones, angle_lut(1.0)).status.numpy()
    assert np.all(status == STATUS["modulation"])
    dark = frames.copy()
    dark[0] = dark[1]
    assert np.all(angle_decode(device, dark, pts, r, sector, zones, angle_lut(1.0)).status.numpy() == STATUS["dark"])


def test_bad_input(device):
    zones = angle_zones(rho0=RHO0, pitch=PITCH, bands=BANDS, sector_bits=SB, min_period_px=12.0)
    frames, _, _ = angle_frames(zones=zones)
    pts, r, a, sector = angle_samples(n=10)
    with pytest.raises(ValueError, match="steps"):
        decode_angle(wp.array(frames, device=device), wp.array(pts.astype(np.float32), dtype=wp.vec2, device=device),
                     wp.array(r.astype(np.float32), device=device), wp.array(sector, device=device), white=0, black=1,
                     angle0=4, steps=4, sector_bits=SB, zones=zones, lut=wp.array(angle_lut(1.0), device=device))
    with pytest.raises(ValueError, match="rho"):
        decode_angle(wp.array(frames, device=device), wp.array(pts.astype(np.float32), dtype=wp.vec2, device=device),
                     wp.array(r[:3].astype(np.float32), device=device), wp.array(sector, device=device), white=0,
                     black=1, angle0=2, steps=4, sector_bits=SB, zones=zones,
                     lut=wp.array(angle_lut(1.0), device=device))


def _sector_frames(ss=4, contrast=200.0):
    """sector_<b>, sector_<b>_inv pairs of the SB-bit Gray code of the polar angle,
    each pixel the lit fraction of its area (ss x ss sub-samples), as drawn."""
    h, w = 300, 400
    o = (np.arange(ss) + 0.5) / ss - 0.5
    y, x = np.mgrid[0:h, 0:w].astype(np.float64)
    ys = y[..., None, None] + o[:, None]
    xs = x[..., None, None] + o[None, :]
    rho = np.hypot(xs - C[0], ys - C[1])
    lit = (rho >= RHO0) & (rho < RHO0 + BANDS * PITCH)
    s = np.floor((np.arctan2(ys - C[1], xs - C[0]) + np.pi) / (2 * np.pi) * 2 ** SB).astype(np.int64) % 2 ** SB
    g = s ^ (s >> 1)
    out = []
    for b in range(SB):
        on = ((g >> (SB - 1 - b)) & 1).astype(bool)
        for f in (on & lit, ~on & lit):
            out.append(np.round(20.0 + contrast * f.mean(axis=(2, 3))).astype(np.uint8))
    return np.stack(out)


def test_unknown_sector_unwraps_from_the_coarse_code_at_the_sample(device):
    """Samples whose pixels' sector did not decode (on a sector edge, or finer sectors
    than the camera resolves) re-read the coarse sector bits at their own position:
    on a sector edge the shared edge unwraps them, and they come back without a slip."""
    zones = angle_zones(rho0=RHO0, pitch=PITCH, bands=BANDS, sector_bits=SB, min_period_px=12.0)
    frames, _, _ = angle_frames(zones=zones)
    stack = np.concatenate([frames, _sector_frames()])
    sector0 = frames.shape[0]
    rng = np.random.default_rng(5)
    n = 3000
    r = rng.uniform(RHO0 + 2, RHO0 + BANDS * PITCH - 2, n)
    P = angle_periods(r, *zones)
    # on the edges of the coarse sectors (2P of them), within a tenth of a pixel
    k = rng.integers(0, 2 * P)
    a = np.angle(np.exp(1j * (k * np.pi / P - np.pi + rng.uniform(-0.1, 0.1, n) / r)))
    pts = np.c_[C[0] + r * np.cos(a), C[1] + r * np.sin(a)]
    inside = (pts[:, 0] > 1) & (pts[:, 0] < 398) & (pts[:, 1] > 1) & (pts[:, 1] < 298)
    edge = np.min(np.abs(r[:, None] - zones[0][None, 1:]), axis=1) < 1.5
    keep = inside & ~edge & (P > 1)
    pts, r, a = pts[keep], r[keep], a[keep]
    unknown = np.full(len(r), -1)
    A = decode_angle(wp.array(stack, device=device), wp.array(pts.astype(np.float32), dtype=wp.vec2, device=device),
                     wp.array(r.astype(np.float32), device=device), wp.array(unknown.astype(np.int32), device=device),
                     white=0, black=1, angle0=2, steps=STEPS, sector_bits=SB, zones=zones,
                     lut=wp.array(angle_lut(1.0), device=device), sector0=sector0)
    st = A.status.numpy()
    assert np.mean(st == STATUS["ok"]) > 0.99
    ok = st == STATUS["ok"]
    err_tan = np.abs(np.angle(np.exp(1j * (A.phi.numpy()[ok] - a[ok])))) * r[ok]
    assert err_tan.max() < 0.3   # no period slip (a period is >= 12 px)
    # without the sector frames they have no angle, as before
    B = angle_decode(device, frames, pts, r, unknown, zones, angle_lut(1.0))
    assert np.all(B.status.numpy() == STATUS["no_sector"])
    # the coarse code unreadable (every sector frame equal to its inverse): no angle, no guess
    flat = stack.copy()
    flat[sector0:] = 120
    C2 = decode_angle(wp.array(flat, device=device), wp.array(pts.astype(np.float32), dtype=wp.vec2, device=device),
                      wp.array(r.astype(np.float32), device=device), wp.array(unknown.astype(np.int32), device=device),
                      white=0, black=1, angle0=2, steps=STEPS, sector_bits=SB, zones=zones,
                      lut=wp.array(angle_lut(1.0), device=device), sector0=sector0)
    assert np.all(C2.status.numpy() == STATUS["no_sector"])
    with pytest.raises(ValueError, match="sector frames"):
        decode_angle(wp.array(frames, device=device), wp.array(pts.astype(np.float32), dtype=wp.vec2, device=device),
                     wp.array(r.astype(np.float32), device=device), wp.array(unknown.astype(np.int32), device=device),
                     white=0, black=1, angle0=2, steps=STEPS, sector_bits=SB, zones=zones,
                     lut=wp.array(angle_lut(1.0), device=device), sector0=sector0)
