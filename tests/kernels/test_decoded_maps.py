"""The decoded codec's kernel (kernels.decoded_maps) against its NumPy statement
(pipeline.codecs.decoded.decoded_samples)."""

from __future__ import annotations

import numpy as np
import pytest
import warp as wp

from ringscan.kernels import init_warp
from ringscan.kernels.decoded_maps import decoded_map_samples
from ringscan.pipeline.calibrate.importer import encode_decoded
from ringscan.pipeline.codecs.decoded import _map_params, decoded_samples
from ringscan.pipeline.formats.patterns import DECODED_SCALE, decoded_scale, parse_patterns


@pytest.mark.parametrize("projector", [(1024, 768), (3840, 2160)])
def test_the_codec_kernel_gives_decoded_samples_figures(projector):
    """The codec's stage (kernels.decoded_maps.decoded_map_samples: count, scan, write on the device) reads
    the fixed-point frames as decoded_samples reads their float maps: the same samples, field by field,
    with and without sectors (sub-pixel and integer codes, undecoded pixels, dim and bright); a 4K projector's
    maps at its own scale (16 steps a px: a coordinate up to 3839.5 fits 16 bits)."""
    init_warp()
    pw, ph = projector
    scale = decoded_scale(pw, ph)
    assert scale == (DECODED_SCALE if pw < 2048 else 16)
    rng = np.random.default_rng(3)
    h, w = 37, 53
    u = rng.uniform(-0.5, pw - 0.5, (h, w))
    v = rng.uniform(-0.5, ph - 0.5, (h, w))
    some = rng.random((h, w)) < 0.3
    u[some] = np.round(u[some])  # some integer codes
    v[::4] = np.round(v[::4])
    u[rng.random((h, w)) < 0.2] = np.nan
    c = rng.uniform(2, 200, (h, w))
    fu, fv, fc = encode_decoded(u, v, c, scale)
    ok = (fu > 0) & (fv > 0)
    assert np.array_equal(ok, np.isfinite(u) & np.isfinite(v))  # every coordinate kept, the far ones too
    for bits in (0, 3):
        spec = parse_patterns({"codec": "decoded", "width": pw, "height": ph, "center": [pw / 2 - 0.5, ph / 2 - 0.5],
                               "rho0": 0.0, "pitch": 1.0, "sector_bits": bits, "scale": scale}, source="test")
        got = decoded_map_samples(wp.array(np.stack([fu, fv, fc]), dtype=wp.uint16, device="cpu"),
                                  params=_map_params(spec), threads=2).numpy()
        want = decoded_samples(np.where(ok, fu / scale - 1.0, np.nan), np.where(ok, fv / scale - 1.0, np.nan),
                               fc / 257.0, center=spec.center, sector_bits=bits, scale=scale)
        assert 0.5 * h * w < len(want["pixel"]) < h * w
        for k, a in want.items():
            # float64 in both, cast to float32 once: equal but for a last float32 digit where C's and
            # NumPy's float64 functions part (hypot against the square root, atan2)
            if a.dtype.kind == "f":
                np.testing.assert_allclose(got[k], a, rtol=2e-7, atol=0, err_msg=k)
            else:
                assert np.array_equal(got[k], a), k


def test_samples_for_matching_leave_out_the_light_gradient_only():
    """Without the light's gradient (camera 2 of a two-camera view: ``DecodedCodec.extract_for_matching``) the
    samples are the same to the bit, field by field, and ``shading`` is None."""
    init_warp()
    rng = np.random.default_rng(5)
    h, w = 29, 41
    u = rng.uniform(0, 1023, (h, w))
    v = rng.uniform(0, 767, (h, w))
    u[rng.random((h, w)) < 0.2] = np.nan
    fu, fv, fc = encode_decoded(u, v, rng.uniform(2, 200, (h, w)))
    frames = wp.array(np.stack([fu, fv, fc]), dtype=wp.uint16, device="cpu")
    spec = parse_patterns({"codec": "decoded", "width": 1024, "height": 768, "center": [511.5, 383.5], "rho0": 0.0,
                           "pitch": 1.0, "sector_bits": 3}, source="test")
    full = decoded_map_samples(frames, params=_map_params(spec), threads=2)
    lean = decoded_map_samples(frames, params=_map_params(spec, light_gradient=False), threads=2)
    assert full.shading is not None and np.all(np.isfinite(full.shading.numpy())) and lean.shading is None
    a, b = full.numpy(), lean.numpy()
    assert set(a) - set(b) <= {"shading"} and len(b["pixel"]) == len(a["pixel"]) > 0
    for k in b:
        assert np.array_equal(a[k], b[k]), k


def test_a_subpixel_coordinate_on_the_integer_grid_is_written_beside_it():
    """The maps hold 1 / scale px steps, and a whole-pixel value means an integer code (the reader gives it an
    integer code's sigma, 1 / sqrt 12 px): a sub-pixel coordinate that rounds onto a whole pixel (1 in 32 of
    them) is written one step beside it, on its own side; integer codes stay whole; nothing moves more than
    one step. The sides that fit: 32 steps a px up to 2047 px, 16 up to 4095, ... 1 up to 65534."""
    from ringscan.pipeline.codecs.decoded import SIGMA_INTEGER_PX, coordinate_sigma

    rng = np.random.default_rng(8)
    x = rng.uniform(0, 1000, 20000)
    x[:100] = np.round(x[:100])  # integer codes
    x[100:200] = np.round(x[100:200]) + rng.choice([-1, 1], 100) * rng.uniform(1e-6, 0.5 / 32, 100)  # near one
    for scale in (32, 16):
        fu, _, _ = encode_decoded(x[None, :], x[None, :], np.full((1, x.size), 50.0), scale)
        back = fu[0] / scale - 1.0
        assert np.max(np.abs(back - x)) <= 1.0 / scale + 1e-9
        whole = fu[0] % scale == 0
        assert whole[:100].all() and not whole[100:].any()
        sigma = coordinate_sigma(back, np.full(x.size, 50.0), scale)
        assert (sigma[:100] == SIGMA_INTEGER_PX).all() and (sigma[100:] < 0.1).all()
    assert [decoded_scale(w, 10) for w in (2047, 2048, 4095, 4096, 65534)] == [32, 16, 16, 8, 1]
    with pytest.raises(ValueError, match="65535"):
        decoded_scale(10, 65535)
