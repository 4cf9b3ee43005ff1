"""kernels.sample_light: each sample's edge sigma, indirect share and frame noise on the frames' device, the
same values to the bit as their NumPy statements (pipeline.codecs.angle_code), a planted floor and a planted
noise read."""

import numpy as np
import pytest
import warp as wp

from ringscan.kernels.ring_labels import decode_gray_rings
from ringscan.kernels.sample_light import phase_light, sample_light, sample_pair_noise, widen_for_pair_noise
from ringscan.pipeline.codecs.angle_code import (
    EDGE_WIDTH_PX,
    edge_sigma,
    noise_pairs,
    pair_noise,
    phase_sigma,
    sample_contrast,
    sample_indirect,
)
from ringscan.pipeline.codecs.shading import sample_shading
from ringscan.pipeline.formats.patterns import frame_names
from tests.support.ring_frames import frame_stack, gray_rings_spec


@pytest.mark.parametrize("dtype", [np.uint8, np.uint16])
def test_the_kernel_reads_what_the_numpy_statements_read(dtype):
    spec = gray_rings_spec()
    rng = np.random.default_rng(4)
    frames = frame_stack(spec, blur=1.5, dtype=dtype)
    # a darker, noisier camera: contrast and floors that vary from pixel to pixel
    scale = 257 if dtype == np.uint16 else 1
    noisy = np.clip(frames.astype(np.float64) * 0.6 + rng.normal(20 * scale, 6 * scale, frames.shape), 0,
                    np.iinfo(dtype).max).astype(dtype)
    fw = wp.array(noisy, device="cpu")
    labels = decode_gray_rings(fw, bits=spec.bits, sector_bits=spec.sector_bits)
    h, w = noisy.shape[1:]
    # positions anywhere, the image's borders and past them included (clamped alike)
    uv = np.concatenate([rng.uniform([-2, -2], [w + 2, h + 2], (3000, 2)),
                         [[0, 0], [w - 1, h - 1], [w - 1.0005, 5.5], [3.5, h - 1.0002], [w + 3, -4]]]).astype(np.float32)
    names = frame_names(spec)
    bits = range(spec.bits - 1, spec.bits - 3, -1)  # angle_code.INDIRECT_BITS, the finest first
    noise = 1.7
    sigma, indirect, shading = sample_light(fw, labels.contrast, wp.array(uv, dtype=wp.vec2), white=names.index("white"),
                                   black=names.index("black"),
                                   pairs=[(names.index(f"gray_{b}"), names.index(f"gray_{b}_inv")) for b in bits],
                                   edge_num=np.sqrt(2.0) * noise * EDGE_WIDTH_PX, threads=2)
    expect_sigma = np.asarray(edge_sigma(sample_contrast(fw, spec, uv, contrast=labels.contrast), noise), np.float32)
    np.testing.assert_array_equal(sigma.numpy(), expect_sigma)
    np.testing.assert_array_equal(indirect.numpy(), sample_indirect(fw, spec, uv))
    expect_shading = sample_shading(labels.contrast.numpy(), uv, scale)
    assert np.count_nonzero(expect_shading > 0.05) > 100  # the blurred rings' light changes across the image
    np.testing.assert_array_equal(shading.numpy(), expect_shading)
    # phase-rings' sigma of rho from its fringes' modulation (some below the 1e-3 floor, some over 1)
    mod = np.concatenate([rng.uniform(0.0, 1.2, len(uv) - 3), [0.0, 5e-4, 1e-3]]).astype(np.float32)
    psig, pind, pshade = phase_light(fw, labels.contrast, wp.array(uv, dtype=wp.vec2), wp.array(mod, dtype=wp.float32),
                             white=names.index("white"), black=names.index("black"),
                             pairs=[(names.index(f"gray_{b}"), names.index(f"gray_{b}_inv")) for b in bits],
                             noise=noise, pitch=4.0, steps=4, smooth_radius=1, threads=2)
    expect = phase_sigma(sample_contrast(fw, spec, uv, contrast=labels.contrast), mod, noise, pitch=4.0, steps=4,
                         smooth_radius=1)
    np.testing.assert_array_equal(psig.numpy(), np.asarray(expect, np.float32))
    np.testing.assert_array_equal(pind.numpy(), sample_indirect(fw, spec, uv))
    np.testing.assert_array_equal(pshade.numpy(), expect_shading)


def test_a_planted_floor_is_read_as_its_share_of_white_minus_black():
    """White 200, black 20; the two finest pairs' darker frames at 65 and 47: a floor (mean 56) 36 above
    black, 0.2 of the 180 span."""
    spec = gray_rings_spec()
    names = frame_names(spec)
    frames = np.full((len(names), 8, 8), 120, np.uint8)
    frames[names.index("white")], frames[names.index("black")] = 200, 20
    pairs = [(names.index(f"gray_{b}"), names.index(f"gray_{b}_inv")) for b in (3, 2)]
    frames[pairs[0][1]], frames[pairs[1][0]] = 65, 47
    sigma, indirect, _ = sample_light(wp.array(frames, device="cpu"), wp.full((8, 8), 180.0, dtype=wp.float32),
                                   wp.array(np.array([[3.2, 4.7]], np.float32), dtype=wp.vec2), white=0, black=1,
                                   pairs=pairs, edge_num=2.0)
    assert indirect.numpy()[0] == pytest.approx(0.2, abs=1e-6)
    assert sigma.numpy()[0] == pytest.approx(2.0 / 360.0, rel=1e-6)  # edge_num / (2 x contrast 180)


def test_bad_arguments_are_refused():
    f = wp.zeros((4, 6, 8), dtype=wp.uint8)
    uv = wp.zeros(2, dtype=wp.vec2)
    with pytest.raises(ValueError, match="contrast must be"):
        sample_light(f, wp.zeros((6, 7), dtype=wp.float32), uv, white=0, black=1, pairs=[(2, 3)], edge_num=1.0)
    with pytest.raises(ValueError, match="frame pairs"):
        sample_light(f, wp.zeros((6, 8), dtype=wp.float32), uv, white=0, black=1, pairs=[], edge_num=1.0)


@pytest.mark.parametrize("dtype", [np.uint8, np.uint16])
def test_the_shading_is_the_lights_relative_gradient(dtype):
    """White - black = 40 exp(0.3 x - 0.1 y) levels (an exponential ramp: its log's gradient is (0.3, -0.1)
    everywhere): each direction's sides differ by exp(+-2 x that) around the pixel, their difference over
    their sum is tanh of the log's gradient, |(tanh 0.3, tanh 0.1)| per px at every inner pixel (sqrt(0.1)
    to 3 %), the border's read one px inside; a flat light reads 0; light under a level is taken as one
    (dark pixels read no slope)."""
    scale = 257.0 if dtype == np.uint16 else 1.0
    yy, xx = np.mgrid[0:12, 0:16].astype(np.float64)
    ramp = (40.0 * np.exp(0.3 * xx - 0.1 * yy) * scale).astype(np.float32)
    frames = wp.zeros((4, 12, 16), dtype=wp.uint8 if dtype == np.uint8 else wp.uint16, device="cpu")
    uv = np.array([[5.2, 4.7], [0.0, 0.0], [15.4, 11.0], [9.0, 6.49]], np.float32)
    for plane, want in ((ramp, np.hypot(np.tanh(0.3), np.tanh(0.1))), (np.full((12, 16), 90.0 * scale, np.float32), 0.0),
                        (np.full((12, 16), 0.3 * scale, np.float32), 0.0)):
        _, _, shading = sample_light(frames, wp.array(plane, device="cpu"), wp.array(uv, dtype=wp.vec2), white=0,
                                     black=1, pairs=[(2, 3)], edge_num=1.0)
        # float32 levels, a float32 result: ~1e-6 relative
        np.testing.assert_allclose(shading.numpy(), want, rtol=1e-5, atol=1e-6)


@pytest.mark.parametrize("dtype", [np.uint8, np.uint16])
def test_the_pair_noise_kernel_is_its_numpy_statement(dtype):
    """sample_pair_noise against angle_code.pair_noise, to the bit: blurred rings with noise that changes
    across the image, samples anywhere (the window cut at the image's borders, past them clamped)."""
    spec = gray_rings_spec()
    rng = np.random.default_rng(5)
    frames = frame_stack(spec, blur=1.5, dtype=dtype)
    scale = 257 if dtype == np.uint16 else 1
    h, w = frames.shape[1:]
    sd = np.linspace(1.0, 8.0, w)[None, None, :] * scale
    noisy = np.clip(frames.astype(np.float64) + rng.normal(0.0, 1.0, frames.shape) * sd, 0,
                    np.iinfo(dtype).max).astype(dtype)
    uv = np.concatenate([rng.uniform([-2, -2], [w + 2, h + 2], (2000, 2)),
                         [[0, 0], [w - 1, h - 1], [w + 3, -4], [1.49, 1.51]]]).astype(np.float32)
    pairs = noise_pairs(spec)
    names = frame_names(spec)
    wb = dict(white=names.index("white"), black=names.index("black"))
    got = sample_pair_noise(wp.array(noisy, device="cpu"), wp.array(uv, dtype=wp.vec2), **wb, pairs=pairs, threads=2)
    np.testing.assert_array_equal(got.numpy(), pair_noise(noisy, uv, wb["white"], wb["black"], pairs))
    assert np.count_nonzero(got.numpy() > 0) > 0.6 * len(uv)  # most windows hold pixels with two clear pairs


def test_the_pair_noise_reads_the_cameras_noise_where_it_is():
    """A pattern and its inverse, one lit and one dark at each pixel (any pattern: here random bits), under
    Gaussian noise of 1.5 levels on the left half and 4.5 on the right: each sample reads its half's noise,
    to the estimate's own scatter (5 x 5 pixels x 6 degrees of freedom: 150, so 1 / sqrt(300) = 6 % a
    sample; 4 standard deviations allowed, 25 %), however the pattern runs. Then one pair mixed at every
    pixel (a 60 / 40 share of the light, seen through a gamma-2.2 camera: their sum is far from the
    unmixed one) is left out: the same noise is read."""
    rng = np.random.default_rng(6)
    h, w, k = 40, 80, 7
    bits = rng.integers(0, 2, (k, h, w)).astype(np.float64)
    lit, dark = 180.0, 30.0
    pattern = dark + (lit - dark) * bits
    frames = np.empty((2 * k + 2, h, w))
    frames[0:2 * k:2], frames[1:2 * k:2] = pattern, lit + dark - pattern
    frames[2 * k], frames[2 * k + 1] = lit, dark
    sd = np.where(np.arange(w) < w // 2, 1.5, 4.5)[None, None, :]
    frames = np.clip(np.rint(frames + rng.normal(0.0, 1.0, frames.shape) * sd), 0, 255).astype(np.uint8)
    uv = np.array([[x, y] for y in (10.0, 20.0, 30.0) for x in (8.0, 15.0, 30.0, 50.0, 62.0, 71.0)], np.float32)
    pairs = [(2 * j, 2 * j + 1) for j in range(k)]
    got = sample_pair_noise(wp.array(frames, device="cpu"), wp.array(uv, dtype=wp.vec2), white=2 * k, black=2 * k + 1,
                            pairs=pairs).numpy()
    want = np.where(uv[:, 0] < w // 2, 1.5, 4.5)
    np.testing.assert_allclose(got, want, rtol=0.25)
    # the mean of the 9 samples on each side: to 6 % / 3 = 2 % (4 of its deviations: 8 %)
    for side in (uv[:, 0] < w // 2, uv[:, 0] >= w // 2):
        assert got[side].mean() == pytest.approx(want[side][0], rel=0.08)
    enc = lambda x: 255.0 * (x / 255.0) ** (1 / 2.2)  # noqa: E731
    mixed = frames.copy()
    mixed[0], mixed[1] = enc(0.6 * 255.0), enc(0.4 * 255.0)  # 200 + 168: 160 levels over lit + dark
    again = sample_pair_noise(wp.array(mixed, device="cpu"), wp.array(uv, dtype=wp.vec2), white=2 * k,
                              black=2 * k + 1, pairs=pairs).numpy()
    np.testing.assert_allclose(again, want, rtol=0.25)


def test_a_sigma_grows_by_its_noise_over_the_views_never_shrinks():
    noise = wp.array(np.array([1.0, 2.0, 4.0, 8.0, 0.0], np.float32), dtype=wp.float32)
    s_rho = wp.array(np.array([0.1, 0.2, 0.3, 0.4, 0.5], np.float32), dtype=wp.float32)
    s_tan = wp.array(np.array([1.0, 1.0, 1.0, 1.0, 1.0], np.float32), dtype=wp.float32)
    rho, none, tan = widen_for_pair_noise(noise, [s_rho, None, s_tan], reference=2.0)
    assert none is None
    np.testing.assert_allclose(rho.numpy(), [0.1, 0.2, 0.6, 1.6, 0.5], rtol=1e-6)  # float32 of the float64 product
    np.testing.assert_allclose(tan.numpy(), [1.0, 1.0, 2.0, 4.0, 1.0], rtol=1e-6)
    with pytest.raises(ValueError, match="reference must be > 0"):
        widen_for_pair_noise(noise, [s_rho], reference=0.0)
    with pytest.raises(ValueError, match="frame pairs"):
        sample_pair_noise(wp.zeros((4, 6, 8), dtype=wp.uint8), wp.zeros(2, dtype=wp.vec2), white=2, black=3,
                          pairs=[(0, 1)])
