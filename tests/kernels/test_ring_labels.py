"""Decode of gray-rings + sectors, per pixel, against the pattern's own geometry."""

import math

import numpy as np
import pytest
import warp as wp

from ringscan.kernels.ring_labels import decode_gray_rings
from ringscan.kernels.settings import DecodeSettings
from tests.support.ring_frames import frame_stack, gray_rings_spec


@pytest.mark.parametrize("dtype", [np.uint8, np.uint16])
def test_decode_matches_band_and_sector_truth(device, dtype):
    spec = gray_rings_spec()
    frames = wp.array(frame_stack(spec, blur=0.6, dtype=dtype), device=device)
    lab = decode_gray_rings(frames, bits=spec.bits, sector_bits=spec.sector_bits)
    band, sector = lab.band.numpy(), lab.sector.numpy()
    v, u = np.mgrid[0:spec.height, 0:spec.width]
    rho = np.hypot(u - spec.center[0], v - spec.center[1])
    phi = np.arctan2(v - spec.center[1], u - spec.center[0])
    k_true = np.floor((rho - spec.rho0) / spec.pitch).astype(int)
    s_true = np.floor((phi + math.pi) / (2 * math.pi) * 2 ** spec.sector_bits).astype(int)
    # Pixels well inside a band and a sector (away from edges and the annulus rims).
    frac = (rho - spec.rho0) / spec.pitch - k_true
    inside = (k_true >= 0) & (k_true < 2 ** spec.bits) & (frac > 0.3) & (frac < 0.7) & (rho < min(spec.width, spec.height) / 2 - 2)
    sfrac = (phi + math.pi) / (2 * math.pi) * 2 ** spec.sector_bits - s_true
    s_inside = inside & (sfrac > 0.1) & (sfrac < 0.9) & (rho > 12)
    assert inside.sum() > 1000
    assert np.array_equal(band[inside], k_true[inside])
    assert np.array_equal(sector[s_inside], s_true[s_inside])
    # Decoded pixels are never mislabelled, wherever they are.
    dec = (band >= 0) & (k_true >= 0) & (k_true < 2 ** spec.bits)
    assert np.all(np.abs(band[dec] - k_true[dec]) <= 1)
    assert np.mean(band[dec] == k_true[dec]) > 0.97


def test_decode_rejects_low_contrast_and_outside(device):
    spec = gray_rings_spec()
    st = frame_stack(spec)
    st[:, :40, :] = 100  # a flat, unlit strip: white == black
    lab = decode_gray_rings(wp.array(st, device=device), bits=spec.bits, sector_bits=spec.sector_bits)
    band = lab.band.numpy()
    assert np.all(band[:40] == -1)
    assert np.all(lab.sector.numpy()[:40] == -1)
    # Outside the coded annulus (the centre disc) frame == inverse: weak bits, no label.
    assert band[59, 79] == -1 and lab.weak.numpy()[59, 79] != 0


def test_decode_empty_image(device):
    fr = wp.zeros((10, 0, 0), dtype=wp.uint8, device=device)
    lab = decode_gray_rings(fr, bits=4)
    assert lab.band.shape == (0, 0)


def test_decode_bad_input(device):
    with pytest.raises(ValueError, match="uint8 or uint16"):
        decode_gray_rings(wp.zeros((10, 4, 4), dtype=wp.float32, device=device), bits=4)
    with pytest.raises(ValueError, match="need 10 frames"):
        decode_gray_rings(wp.zeros((6, 4, 4), dtype=wp.uint8, device=device), bits=4)
    with pytest.raises(ValueError, match="3D Warp array"):
        decode_gray_rings(np.zeros((10, 4, 4), np.uint8), bits=4)
    with pytest.raises(ValueError, match="bits"):
        decode_gray_rings(wp.zeros((40, 4, 4), dtype=wp.uint8, device=device), bits=0)


def test_decode_threads_agree():
    spec = gray_rings_spec()
    frames = wp.array(frame_stack(spec, blur=0.8), device="cpu")
    a = decode_gray_rings(frames, bits=spec.bits, sector_bits=spec.sector_bits, threads=1)
    b = decode_gray_rings(frames, bits=spec.bits, sector_bits=spec.sector_bits, threads=3)
    assert np.array_equal(a.band.numpy(), b.band.numpy())
    assert np.array_equal(a.sector.numpy(), b.sector.numpy())


def test_eight_pixel_words_match_pixel_kernel(device):
    """The 8-bit decode runs on uint64 words (eight pixels at once) where the width
    is a multiple of 8, else one pixel at a time: both give the same labels."""
    rng = np.random.default_rng(3)
    st = rng.integers(0, 256, size=(2 + 2 * 5 + 2 * 3, 20, 64), dtype=np.uint8)
    st[0] = np.maximum(st[0], 150)
    st[1] = np.minimum(st[1], 60)
    wide = np.concatenate([st, st[:, :, :1]], axis=2)  # width 65: the per-pixel kernel
    for margin in (0.0, 0.12, 0.5, 2.0):
        s = DecodeSettings(bit_margin=margin)
        a = decode_gray_rings(wp.array(st, device=device), bits=5, sector_bits=3, settings=s)
        b = decode_gray_rings(wp.array(wide, device=device), bits=5, sector_bits=3, settings=s)
        for name in ("code", "weak", "band", "sector", "contrast"):
            assert np.array_equal(getattr(a, name).numpy(), getattr(b, name).numpy()[:, :64]), (margin, name)


@pytest.mark.parametrize("bits,sector_bits", [(1, 0), (7, 6), (15, 12)])
def test_eight_pixel_words_match_pixel_kernel_any_contrast(device, bits, sector_bits):
    """Word and pixel decodes agree over the whole range: negative and small
    contrasts, contrast thresholds between and on integers, the widest codes."""
    rng = np.random.default_rng(bits)
    st = rng.integers(0, 256, size=(2 + 2 * bits + 2 * sector_bits, 12, 64), dtype=np.uint8)
    st[0, :6] = np.minimum(255, st[1, :6].astype(int) + rng.integers(0, 40, size=(6, 64))).astype(np.uint8)
    wide = np.concatenate([st, st[:, :, :1]], axis=2)  # width 65: the per-pixel kernel
    for s in (DecodeSettings(), DecodeSettings(min_contrast=0.0, bit_margin=0.07),
              DecodeSettings(min_contrast=12.5, bit_margin=0.25), DecodeSettings(min_contrast=-20.0, bit_margin=1.0),
              DecodeSettings(min_contrast=300.0)):
        a = decode_gray_rings(wp.array(st, device=device), bits=bits, sector_bits=sector_bits, settings=s)
        b = decode_gray_rings(wp.array(wide, device=device), bits=bits, sector_bits=sector_bits, settings=s)
        for name in ("code", "weak", "band", "sector", "contrast"):
            assert np.array_equal(getattr(a, name).numpy(), getattr(b, name).numpy()[:, :64]), (s, name)
        assert (a.band.numpy() >= 0).any() == (s.min_contrast < 255)


def test_frames_off_an_eight_byte_boundary_decode_a_pixel_at_a_time(device):
    """Frames whose first pixel is not 8-byte aligned (memory from elsewhere: a
    tensor at an odd offset) have no uint64 view (a CUDA 64-bit load there faults):
    they decode with the pixel kernel, to the same labels."""
    from ringscan.kernels.ring_labels import as_words

    rng = np.random.default_rng(5)
    st = rng.integers(0, 256, size=(2 + 2 * 4 + 2 * 2, 8, 32), dtype=np.uint8)
    st[0] = np.maximum(st[0], 150)
    st[1] = np.minimum(st[1], 60)
    base = wp.array(np.concatenate([np.zeros(8, np.uint8), st.ravel()]), device=device)
    aligned = wp.array(st, device=device)
    assert as_words(aligned) is not None and aligned.ptr % 8 == 0
    for off in (1, 3, 8):
        fr = wp.array(ptr=base.ptr + off, dtype=wp.uint8, shape=st.shape, device=device)
        fr._ref = base
        wp.copy(fr, aligned)
        assert (as_words(fr) is None) == (off % 8 != 0)
        a = decode_gray_rings(aligned, bits=4, sector_bits=2)
        b = decode_gray_rings(fr, bits=4, sector_bits=2)
        for name in ("code", "weak", "band", "sector", "contrast"):
            assert np.array_equal(getattr(a, name).numpy(), getattr(b, name).numpy()), (off, name)


@pytest.mark.parametrize("blur,dtype", [(0.0, np.uint8), (6.0, np.uint8), (3.0, np.uint16)])
def test_label_counts_on_the_device_are_the_numpy_statements(blur, dtype):
    """count_labels (one row a thread, an (H, 3) read) against the NumPy statement of the low-modulation
    test (pipeline.codecs.gray_rings.low_modulation_pixels) and the decoded count, with half the frame
    dark (unlit pixels beside lit ones) so that every branch of the test is taken."""
    from ringscan.kernels.ring_labels import count_labels
    from ringscan.pipeline.codecs.gray_rings import low_modulation_pixels

    spec = gray_rings_spec()
    frames = frame_stack(spec, blur=blur, dtype=dtype)
    frames[:, :, : frames.shape[2] // 3] //= 32  # a dark third: contrast below the threshold there
    labels = decode_gray_rings(wp.array(frames, device="cpu"), bits=spec.bits, sector_bits=spec.sector_bits)
    mc = 12.0 * (257 if dtype == np.uint16 else 1)
    decoded, lit, low = count_labels(labels, bits=spec.bits, min_contrast=mc, threads=2)
    expect_low, expect_lit = low_modulation_pixels(labels, bits=spec.bits, min_contrast=mc)
    assert (decoded, lit, low) == (int(np.count_nonzero(labels.band.numpy() >= 0)), expect_lit, expect_low)
    assert 0 < lit < frames.shape[1] * frames.shape[2] and (low > 0) == (blur >= 3.0)
