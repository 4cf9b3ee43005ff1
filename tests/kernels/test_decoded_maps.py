"""The decoded codec's kernel (kernels.decoded_maps) against its NumPy statement
(pipeline.codecs.decoded.decoded_samples)."""

from __future__ import annotations

import numpy as np
import warp as wp

from ringscan.kernels import init_warp
from ringscan.kernels.decoded_maps import decoded_map_samples
from ringscan.pipeline.calibrate.importer import encode_decoded
from ringscan.pipeline.codecs.decoded import _map_params, decoded_samples
from ringscan.pipeline.formats.patterns import DECODED_SCALE, parse_patterns


def test_the_codec_kernel_gives_decoded_samples_figures():
    """The codec's stage (kernels.decoded_maps.decoded_map_samples: count, scan, write on the device) reads
    the fixed-point frames as decoded_samples reads their float maps: the same samples, field by field,
    with and without sectors (sub-pixel and integer codes, undecoded pixels, dim and bright)."""
    init_warp()
    rng = np.random.default_rng(3)
    h, w = 37, 53
    u = rng.uniform(0, 1023, (h, w))
    v = rng.uniform(0, 767, (h, w))
    some = rng.random((h, w)) < 0.3
    u[some] = np.round(u[some])  # some integer codes
    v[::4] = np.round(v[::4])
    u[rng.random((h, w)) < 0.2] = np.nan
    c = rng.uniform(2, 200, (h, w))
    fu, fv, fc = encode_decoded(u, v, c)
    for bits in (0, 3):
        spec = parse_patterns({"codec": "decoded", "width": 1024, "height": 768, "center": [511.5, 383.5],
                               "rho0": 0.0, "pitch": 1.0, "sector_bits": bits}, source="test")
        got = decoded_map_samples(wp.array(np.stack([fu, fv, fc]), dtype=wp.uint16, device="cpu"),
                                  params=_map_params(spec), threads=2).numpy()
        ok = (fu > 0) & (fv > 0)
        want = decoded_samples(np.where(ok, fu / DECODED_SCALE - 1.0, np.nan), np.where(ok, fv / DECODED_SCALE - 1.0,
                               np.nan), fc / 257.0, center=spec.center, sector_bits=bits)
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
