"""Phase-rings kernels against the pattern's own geometry (camera = projector grid)."""

import math

import numpy as np
import pytest
import warp as wp

from ringscan.kernels.phase import (
    PHASE_STATUS_NAMES,
    PhaseMap,
    compact_phase_points,
    decode_phase,
    drop_lone_fringes,
    smooth_phase,
)
from ringscan.kernels.response import response_tables
from ringscan.kernels.settings import PhaseSettings
from ringscan.kernels.ring_labels import decode_gray_rings
from ringscan.pipeline.formats.patterns import frame_names, gray_decode
from tests.support.phase_frames import phase_decode, phase_spec, phase_stack

STATUS = {n: i for i, n in enumerate(PHASE_STATUS_NAMES)}


def _truth_t(spec):
    v, u = np.mgrid[0:spec.height, 0:spec.width]
    rho = np.hypot(u - spec.center[0], v - spec.center[1])
    return (rho - spec.rho0) / spec.pitch, rho


def _annulus(spec, rho, margin=1.5):
    far = min(spec.width, spec.height) / 2 - 2
    return (rho > spec.rho0 + margin) & (rho < min(spec.rho_max, far) - margin)


def test_phase_matches_geometry_and_never_slips(device):
    spec = phase_spec()
    t_true, rho = _truth_t(spec)
    _, _, ph = phase_decode(phase_stack(spec, noise=1.0), spec, device, settings=PhaseSettings(smooth_radius=0))
    st, t = ph.status.numpy(), ph.t.numpy()
    ann = _annulus(spec, rho)
    ok = ann & (st == 0)
    assert ok.sum() >= 0.97 * ann.sum()
    err = t[ok] - t_true[ok]
    assert np.abs(err).max() < 0.05, np.abs(err).max()  # no slip anywhere (a slip is a whole band)
    assert np.sqrt(np.mean(err ** 2)) < 0.01
    q = ph.modulation.numpy()[ok]
    assert np.median(q) > 0.8 and q.max() < 1.2
    # Outside the coded annulus there is no point.
    outside = rho > spec.rho_max + 2
    assert not np.any(st[outside] == 0)


def test_unwrapping_at_band_edges_beats_the_naive_rule(device):
    """Strong noise: t = band + wrapped phase slips a period near edges; the
    edge-anchored unwrapping does not."""
    spec = phase_spec()
    t_true, rho = _truth_t(spec)
    fr, lab, ph = phase_decode(phase_stack(spec, noise=5.0, seed=3), spec, device,
                               settings=PhaseSettings(smooth_radius=0))
    st, t = ph.status.numpy(), ph.t.numpy()
    ann = _annulus(spec, rho)
    ok = ann & (st == 0)
    assert ok.sum() > 0.9 * ann.sum()
    assert np.sum(np.abs(t[ok] - t_true[ok]) > 0.5) == 0
    # The plain rule on the same wrapped phase: band index (decoded from the raw
    # code, weak bits and all) + wrapped phase.
    band = gray_decode(lab.code.numpy(), spec.bits)
    naive = band + (t - np.floor(t))
    assert np.sum(np.abs(naive[ok] - t_true[ok]) > 0.5) > 20


@pytest.mark.parametrize("cam_gamma,light_gamma,steps", [(2.2, 1.0, 4), (1.0, 1.8, 3), (2.2, 2.0, 3)])
def test_response_correction_removes_gamma_error(device, cam_gamma, light_gamma, steps):
    spec = phase_spec(steps=steps)
    t_true, rho = _truth_t(spec)
    frames = phase_stack(spec, cam_gamma=cam_gamma, light_gamma=light_gamma, blur=0.0)
    s = PhaseSettings(smooth_radius=0)
    ann = _annulus(spec, rho)

    def rms(cg, lg):
        _, _, ph = phase_decode(frames, spec, device, cam_gamma=cg, light_gamma=lg, settings=s)
        ok = ann & (ph.status.numpy() == 0)
        assert ok.sum() > 0.9 * ann.sum()
        return float(np.sqrt(np.mean((ph.t.numpy()[ok] - t_true[ok]) ** 2)))

    corrected, raw = rms(cam_gamma, light_gamma), rms(1.0, 1.0)
    assert corrected < 0.006, corrected
    assert raw > 3 * corrected, (raw, corrected)


def test_mixed_pixels_are_dropped_for_low_modulation(device):
    spec = phase_spec()
    shifted = phase_spec(rho0=spec.rho0 + spec.pitch / 2)  # opposite fringe phase, same bands
    _, rho = _truth_t(spec)
    _, _, ph = phase_decode(phase_stack(spec, mix_with=shifted), spec, device)
    st = ph.status.numpy()
    ann = _annulus(spec, rho, margin=spec.pitch)
    assert np.mean(st[ann] == STATUS["modulation"]) > 0.95
    assert np.mean(ph.modulation.numpy()[ann] < 0.3) > 0.95


def test_dark_frames_give_no_points(device):
    spec = phase_spec()
    frames = np.zeros((len(frame_names(spec)), spec.height, spec.width), np.uint8)
    fr, lab, ph = phase_decode(frames, spec, device)
    assert np.all(ph.status.numpy() == STATUS["dark"])
    sm = smooth_phase(ph, lab.sector)
    pts = compact_phase_points(sm, rho0=spec.rho0, pitch=spec.pitch)
    assert len(pts) == 0 and pts.uv.shape == (0,)


def test_smoothing_keeps_planes_edges_and_drops_lone_slips(device):
    h, w = 40, 50
    rng = np.random.default_rng(1)
    v, u = np.mgrid[0:h, 0:w]
    ramp = 3.0 + 0.13 * u + 0.05 * v
    ramp[:, 30:] += 0.6  # a depth edge: t jumps by 0.6 band
    noisy = ramp + rng.normal(0, 0.004, ramp.shape)
    status = np.zeros((h, w), np.int32)
    noisy[20, 10] += 1.0  # a lone unwrapping slip
    sector = np.where(u < 25, 3, 4).astype(np.int32)
    sector[:, 25] = -1  # a sector edge: no sector decoded
    ph = PhaseMap(t=wp.array(noisy.astype(np.float32), device=device),
                  modulation=wp.array(np.full((h, w), 0.9, np.float32), device=device),
                  status=wp.array(status, device=device))
    sm = smooth_phase(ph, wp.array(sector, device=device))
    t, st, sec = sm.t.numpy(), sm.status.numpy(), sm.sector.numpy()
    assert st[20, 10] == STATUS["lonely"]
    inner = (u > 1) & (u < 28) & (v > 1) & (v < h - 2) & ~((abs(u - 10) <= 1) & (abs(v - 20) <= 1))
    e0 = (noisy - ramp)[inner]
    e1 = (t - ramp)[inner]
    assert np.std(e1) < 0.5 * np.std(e0)
    assert abs(np.mean(e1)) < 0.001
    # Next to the edge: no averaging across it.
    for x in (29, 30):
        assert np.all(np.abs(t[2:-2, x] - ramp[2:-2, x]) < 0.02)
    assert np.all(np.isin(sec[:, 25], (3, 4)))
    pts = compact_phase_points(sm, rho0=2.0, pitch=4.0)
    valid = (st == 0).ravel()
    assert len(pts) == int(valid.sum())
    pix = pts.pixel.numpy()
    assert np.all(np.diff(pix) > 0) and np.array_equal(pix, np.flatnonzero(valid))
    uv = pts.uv.numpy()
    assert np.array_equal(uv[:, 0], pix % w) and np.array_equal(uv[:, 1], pix // w)
    assert np.allclose(pts.rho.numpy(), 2.0 + 4.0 * t.ravel()[pix], atol=1e-4)
    assert np.allclose(pts.confidence.numpy(), 0.9)


@pytest.mark.parametrize("blur", [0.6, 1.0])
def test_ring_curvature_correction_removes_the_outward_bias(device, blur):
    # Averaging across a ring reads rho too large by (tangential variance) / (2 rho):
    # here the blur's sigma^2 plus the 3x3 window's 2/3 px^2, (blur^2 + 2/3) / 2 px x px
    # (rho x rho error). Medians over rho 12..90 (the bias falls as 1 / rho).
    spec = phase_spec()
    t_true, rho = _truth_t(spec)
    _, lab, ph = phase_decode(phase_stack(spec, blur=blur), spec, device)
    expect = (blur ** 2 + 2.0 / 3.0) / 2.0
    for correct in (False, True):
        kw = {"rho0": spec.rho0, "pitch": spec.pitch} if correct else {}
        sm = smooth_phase(ph, lab.sector, **kw)
        m = (sm.status.numpy() == 0) & (rho > 12) & (rho < 90)
        assert m.sum() > 15000
        bias = np.median((sm.t.numpy() - t_true)[m] * spec.pitch * rho[m])
        if correct:
            assert abs(bias) < 0.1 * expect
        else:
            assert bias == pytest.approx(expect, rel=0.15)
    off = smooth_phase(ph, lab.sector, rho0=spec.rho0, pitch=spec.pitch,
                       settings=PhaseSettings(ring_curvature=False))
    plain = smooth_phase(ph, lab.sector)
    assert np.array_equal(off.t.numpy(), plain.t.numpy())
    with pytest.raises(ValueError, match="both"):
        smooth_phase(ph, lab.sector, rho0=spec.rho0)


def test_kernel_matches_numpy_twin(device):
    from ringscan.tools.bench.numpy_twins import decode_numpy, phase_numpy, points_numpy, smooth_numpy

    spec = phase_spec()
    frames = phase_stack(spec, noise=2.0, cam_gamma=2.2, light_gamma=1.3, seed=5)
    fr, lab, ph = phase_decode(frames, spec, device, cam_gamma=2.2, light_gamma=1.3)
    dec = decode_numpy(frames, bits=spec.bits, sector_bits=spec.sector_bits)
    lut, wlut = response_tables(255, camera_gamma=2.2)
    ref = phase_numpy(frames, dec, bits=spec.bits, sector_bits=spec.sector_bits, steps=spec.steps, lut=lut, wlut=wlut,
                      light_gamma=1.3)
    st, rst = ph.status.numpy(), ref["status"]
    assert np.mean(st == rst) > 0.999
    both = (st == 0) & (rst == 0)
    assert both.sum() > 3000
    assert np.allclose(ph.t.numpy()[both], ref["t"][both], atol=2e-4)
    sm = smooth_phase(ph, lab.sector)
    rsm = smooth_numpy(ref, dec["sector"])
    p = compact_phase_points(sm, rho0=spec.rho0, pitch=spec.pitch)
    rp = points_numpy(rsm, rho0=spec.rho0, pitch=spec.pitch)
    common, ia, ib = np.intersect1d(p.pixel.numpy(), rp["pixel"], return_indices=True)
    assert len(common) > 0.99 * max(len(p), len(rp["pixel"]))
    assert np.allclose(p.rho.numpy()[ia], rp["rho"][ib], atol=2e-3)
    assert np.mean(p.sector.numpy()[ia] == rp["sector"][ib]) > 0.999


def test_response_tables():
    lut, wlut = response_tables(255, camera_gamma=2.2)
    assert lut.shape == wlut.shape == (256,)
    assert lut[0] == 0 and lut[255] == pytest.approx(1.0) and lut[128] == pytest.approx((128 / 255) ** 2.2, rel=1e-6)
    # brighter values are noisier once linearised: lower weight
    assert np.all(np.diff(wlut[10:]) < 0) and wlut.max() == pytest.approx(1.0)
    lut1, w1 = response_tables(65535, camera_gamma=1.0)
    assert lut1.shape == (65536,) and np.all(w1 == 1)
    _, wu = response_tables(255, camera_gamma=2.2, weighted=False)
    assert np.all(wu == 1)
    with pytest.raises(ValueError, match="full_scale"):
        response_tables(1023)
    with pytest.raises(ValueError, match="gamma"):
        response_tables(255, camera_gamma=0.0)


def test_bad_inputs(device):
    spec = phase_spec()
    frames = phase_stack(spec)
    fr = wp.array(frames, device=device)
    lab = decode_gray_rings(fr, bits=spec.bits, sector_bits=spec.sector_bits)
    lut, wlut = (wp.array(a, device=device) for a in response_tables(255))
    kw = dict(bits=spec.bits, sector_bits=spec.sector_bits, steps=spec.steps, lut=lut, wlut=wlut)
    with pytest.raises(ValueError, match="uint8/uint16"):
        decode_phase(wp.array(frames.astype(np.float32), device=device), lab, **kw)
    with pytest.raises(ValueError, match="need"):
        decode_phase(wp.array(frames[:-1], device=device), lab, **kw)
    with pytest.raises(ValueError, match="lut"):
        decode_phase(fr, lab, **{**kw, "lut": wp.array(response_tables(65535)[0], device=device)})
    small = decode_gray_rings(wp.array(frames[:, :10, :10].copy(), device=device), bits=spec.bits,
                              sector_bits=spec.sector_bits)
    with pytest.raises(ValueError, match="labels"):
        decode_phase(fr, small, **kw)
    with pytest.raises(ValueError, match="steps"):
        decode_phase(fr, lab, **{**kw, "steps": 2})
    ph = decode_phase(fr, lab, **kw)
    with pytest.raises(ValueError, match="sector"):
        smooth_phase(ph, small.sector)
    with pytest.raises(ValueError, match="smooth_phase first"):
        compact_phase_points(ph, rho0=1.0, pitch=2.0)
    with pytest.raises(ValueError, match="response"):
        PhaseSettings(response="auto")
    with pytest.raises(ValueError, match="smooth_radius"):
        PhaseSettings(smooth_radius=9)


def test_sixteen_bit_frames(device):
    spec = phase_spec()
    t_true, rho = _truth_t(spec)
    frames = (phase_stack(spec).astype(np.uint16) * 257)
    fr = wp.array(frames, device=device)
    lab = decode_gray_rings(fr, bits=spec.bits, sector_bits=spec.sector_bits)
    lut, wlut = (wp.array(a, device=device) for a in response_tables(65535))
    ph = decode_phase(fr, lab, bits=spec.bits, sector_bits=spec.sector_bits, steps=spec.steps, lut=lut, wlut=wlut,
                      settings=PhaseSettings(smooth_radius=0))
    ok = _annulus(spec, rho) & (ph.status.numpy() == 0)
    assert ok.sum() > 0.95 * _annulus(spec, rho).sum()
    assert np.abs(ph.t.numpy()[ok] - t_true[ok]).max() < 0.05
    assert math.isfinite(float(ph.modulation.numpy().max()))


def _lone_fringes_numpy(status, size, share):
    """The NumPy statement the kernel replaced (phase_rings._drop_lone_fringes before issue 33): each
    pixel's share of its lit neighbours dropped for modulation, by SciPy's box filters; a valid pixel above
    ``share`` is dropped."""
    from scipy.ndimage import uniform_filter

    washed = uniform_filter((status == STATUS["modulation"]).astype(np.float32), size=size, mode="constant")
    lit = uniform_filter((status != STATUS["dark"]).astype(np.float32), size=size, mode="constant")
    return (status == STATUS["ok"]) & (washed / np.maximum(lit, 1e-6) > share)


def test_lone_fringes_are_dropped_as_the_box_filters_drop_them():
    """A map of valid fringes, shadows and washed-out patches (modulation) with valid pixels scattered
    through them (the camera's noise passing the test), its edges included: the kernel drops, as
    modulation, the valid pixels the box-filter statement drops, keeps the flags equal to the valid statuses, and
    touches no other status; at an exact tie (half of a square's lit pixels washed) the kernel's counts keep
    the pixel, where the filters' float32 means read a hair over half and dropped it."""
    rng = np.random.default_rng(8)
    h, w = 70, 90
    status = np.zeros((h, w), np.int32)
    status[:, 60:] = STATUS["dark"]
    washed = np.zeros((h, w), bool)
    washed[10:40, 5:50] = True
    washed[50:, 40:75] = True  # across the shadow's edge: its dark pixels are no fringe's
    status[washed & (rng.random((h, w)) > 0.15) & (status == 0)] = STATUS["modulation"]
    status[rng.random((h, w)) < 0.03] = STATUS["slip"]
    status[0, :3] = [STATUS["modulation"], STATUS["modulation"], STATUS["ok"]]  # a corner's clipped square
    tie = np.zeros((5, 5), np.int32)  # 12 of the 25 lit pixels washed and one dark: share exactly 0.5
    tie.flat[[0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11]] = STATUS["modulation"]
    tie[4, 4] = STATUS["dark"]
    status[62:67, 2:7] = tie
    pm = PhaseMap(t=wp.zeros((h, w), dtype=wp.float32), modulation=wp.zeros((h, w), dtype=wp.float32),
                  status=wp.array(status, dtype=wp.int32), sector=wp.zeros((h, w), dtype=wp.int32),
                  flags=wp.array((status == 0).astype(np.int32).ravel(), dtype=wp.int32))
    out = drop_lone_fringes(pm, size=5, share=0.5, threads=2)
    drop = _lone_fringes_numpy(status, 5, 0.5)
    assert 50 < drop.sum() < (status == 0).sum() - 1000  # some dropped, most valid pixels kept
    # the tie: the box filters' float32 means (12 / 25 over 24 / 25) read a hair above 0.5 and drop it; the
    # kernel counts (12 of 24 is not more than half) and keeps it, as LONE_FRINGE_SHARE says
    assert drop[64, 4] and out.status.numpy()[64, 4] == STATUS["ok"]
    drop[64, 4] = False
    np.testing.assert_array_equal(out.status.numpy(), np.where(drop, STATUS["modulation"], status))
    np.testing.assert_array_equal(out.flags.numpy(), (out.status.numpy() == 0).astype(np.int32).ravel())
    assert pm.status.numpy() is not out.status.numpy() and (pm.status.numpy() == status).all()  # input kept
    with pytest.raises(ValueError, match="odd"):
        drop_lone_fringes(pm, size=4, share=0.5)
