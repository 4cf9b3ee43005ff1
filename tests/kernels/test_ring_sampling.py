"""Sub-pixel ring samples land on the pattern's circles (camera = projector grid)."""

import numpy as np
import pytest
import warp as wp

from ringscan.kernels.ring_labels import decode_gray_rings
from ringscan.kernels.ring_sampling import ring_radii, sample_gray_rings
from ringscan.kernels.settings import SampleSettings
from tests.support.ring_frames import frame_stack, gray_rings_spec


@pytest.mark.parametrize("blur", [0.0, 0.8, 1.5])
def test_samples_lie_on_ring_circles(device, blur):
    spec = gray_rings_spec(width=200, height=160, center=(99.3, 79.6), bits=5, pitch=3.0, rho0=5.0)
    frames = wp.array(frame_stack(spec, blur=blur), device=device)
    lab = decode_gray_rings(frames, bits=spec.bits)
    s = sample_gray_rings(frames, lab, bits=spec.bits)
    d = s.numpy()
    assert len(s) > 2000
    r = np.hypot(d["uv"][:, 0] - spec.center[0], d["uv"][:, 1] - spec.center[1])
    r_true = spec.rho0 + d["ring"] * spec.pitch
    err = np.abs(r - r_true)
    # Every sample sits on its own circle (a wrong ring would be >= 3 px off).
    # Away from the image border (where blurring reflects the image) and from the
    # smallest circles (a blurred circle's edge moves inward by ~sigma^2 / 2 rho):
    u, v = d["uv"][:, 0], d["uv"][:, 1]
    away = (u > 5) & (v > 5) & (u < spec.width - 6) & (v < spec.height - 6) & (r_true > 12)
    assert err[away].max() < 0.15
    assert np.median(err) < 0.04
    assert d["ring"].min() >= 1 and d["ring"].max() <= 2 ** spec.bits - 1
    assert np.all((d["confidence"] > 0) & (d["confidence"] <= 1))
    rho = ring_radii(s.ring, rho0=spec.rho0, pitch=spec.pitch).numpy()
    assert np.allclose(rho, r_true)


def test_sample_order_is_deterministic_raster():
    spec = gray_rings_spec()
    frames = wp.array(frame_stack(spec, blur=0.7), device="cpu")
    lab = decode_gray_rings(frames, bits=spec.bits)
    a = sample_gray_rings(frames, lab, bits=spec.bits, threads=1).numpy()
    b = sample_gray_rings(frames, lab, bits=spec.bits, threads=2).numpy()
    assert np.array_equal(a["pixel"], b["pixel"]) and np.array_equal(a["uv"], b["uv"])
    assert np.all(np.diff(a["pixel"]) >= 0)


def test_no_edges_gives_no_samples(device):
    spec = gray_rings_spec()
    st = frame_stack(spec)
    st[2:] = st[2:, :1, :1]  # every code frame flat: no edge anywhere
    frames = wp.array(st, device=device)
    lab = decode_gray_rings(frames, bits=spec.bits)
    s = sample_gray_rings(frames, lab, bits=spec.bits)
    assert len(s) == 0 and s.uv.shape == (0,)


def test_flat_edges_are_dropped(device):
    spec = gray_rings_spec()
    frames = wp.array(frame_stack(spec, blur=3.0), device=device)  # heavy defocus
    lab = decode_gray_rings(frames, bits=spec.bits)
    strict = sample_gray_rings(frames, lab, bits=spec.bits, settings=SampleSettings(min_slope=0.9))
    assert len(strict) == 0


def test_sampling_bad_input(device):
    spec = gray_rings_spec()
    frames = wp.array(frame_stack(spec), device=device)
    lab = decode_gray_rings(frames, bits=spec.bits)
    with pytest.raises(ValueError, match="labels are"):
        sample_gray_rings(wp.zeros((10, 8, 8), dtype=wp.uint8, device=device), lab, bits=4)
    with pytest.raises(ValueError, match="need"):
        sample_gray_rings(frames, lab, bits=9)
    with pytest.raises(ValueError, match="int32"):
        ring_radii(wp.zeros(3, dtype=wp.float32, device=device), rho0=0, pitch=1)


@pytest.mark.parametrize("blur", [1.0, 1.5])
def test_ring_curvature_correction_removes_the_inward_edge_shift(device, blur):
    # A blurred circle's edge (frame = inverse) lies inward of its radius by
    # sigma^2 / (2 rho): the nominal rho reads too large by that. Here sigma is the
    # Gaussian blur (camera = projector grid, point-sampled frames): rho x error
    # = blur^2 / 2. Medians over rho 10..60, away from the image border.
    spec = gray_rings_spec(width=240, height=200, center=(119.3, 99.6), bits=5, pitch=4.0, rho0=5.0)
    frames = wp.array(frame_stack(spec, blur=blur), device=device)
    lab = decode_gray_rings(frames, bits=spec.bits)
    expect = blur ** 2 / 2.0
    for on in (False, True):
        s = sample_gray_rings(frames, lab, bits=spec.bits, rho0=spec.rho0, pitch=spec.pitch,
                              settings=SampleSettings(ring_curvature=on))
        d = s.numpy()
        u, v = d["uv"][:, 0], d["uv"][:, 1]
        r = np.hypot(u - spec.center[0], v - spec.center[1])
        m = (u > 6) & (v > 6) & (u < spec.width - 7) & (v < spec.height - 7) & (d["rho"] > 10) & (d["rho"] < 60)
        assert m.sum() > 2000
        bias = np.median(((d["rho"] - r) * d["rho"])[m])
        if on:
            assert abs(bias) < 0.12 * expect
            # per ring, not per sample: the correction adds no scatter within a ring
            for k in np.unique(d["ring"][m])[:5]:
                assert np.ptp(d["rho"][d["ring"] == k]) < 1e-4
        else:
            assert bias == pytest.approx(expect, rel=0.15)
            assert np.allclose(d["rho"], spec.rho0 + d["ring"] * spec.pitch)
    with pytest.raises(ValueError, match="both"):
        sample_gray_rings(frames, lab, bits=spec.bits, rho0=spec.rho0)


def test_sample_sector_is_its_pairs_sector(device):
    """A sample's sector is its pixel's, or where that has none its neighbour's."""
    spec = gray_rings_spec()
    frames = wp.array(frame_stack(spec, blur=0.7), device=device)
    lab = decode_gray_rings(frames, bits=spec.bits, sector_bits=spec.sector_bits)
    d = sample_gray_rings(frames, lab, bits=spec.bits).numpy()
    sec = lab.sector.numpy()
    y, x = np.divmod(d["pixel"], spec.width)
    along_x = d["uv"][:, 0] != x
    along_y = d["uv"][:, 1] != y
    one = along_x != along_y  # a crossing exactly at the pixel leaves its direction open
    assert one.mean() > 0.95
    y, x, along_x = y[one], x[one], along_x[one]
    q = np.where(along_x, sec[y, np.minimum(x + 1, spec.width - 1)], sec[np.minimum(y + 1, spec.height - 1), x])
    want = np.where(sec[y, x] >= 0, sec[y, x], q)
    assert np.array_equal(d["sector"][one], want)
    assert (want >= 0).mean() > 0.9 and len(np.unique(want[want >= 0])) == 2 ** spec.sector_bits
