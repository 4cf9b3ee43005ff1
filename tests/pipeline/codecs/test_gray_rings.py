"""gray-rings under a light of gamma 2.2: the sub-pixel band boundaries (where a frame
crosses its inverse) are as accurate with frames pre-compensated for the light as with
plain frames and with a linear light (the pair's edges are symmetric either way)."""

import dataclasses
import json

import pytest

from ringscan.pipeline.evaluate.metrics import evaluate_view
from ringscan.pipeline.formats.patterns import parse_patterns
from ringscan.pipeline.reconstruct.view import reconstruct_view
from ringscan.pipeline.simulate.scan import simulate_scan
from tests.support.crop_rig import PROJ, crop_rig

GRAY = {"codec": "gray-rings", **PROJ, "rho0": 8.0, "pitch": 2.0, "bits": 7, "sector_bits": 6}
"""On crop_rig's projector window (test_phase_rings.WINDOW: the camera's frames are the whole projector's)."""


@pytest.fixture(scope="module")
def medians(tmp_path_factory):
    d = tmp_path_factory.mktemp("gray_gamma")
    out = {}
    for name, light_gamma, pre in (("linear", 1.0, 1.0), ("precompensated", 2.2, 2.2), ("plain", 2.2, 1.0)):
        rig = crop_rig()
        rig = dataclasses.replace(rig, light=dataclasses.replace(rig.light, gamma=light_gamma))
        spec = parse_patterns({**GRAY, "precompensated_gamma": pre})
        scan = simulate_scan(d / name, scene="sphere", rig=rig, patterns=spec, progress=False)
        cloud = reconstruct_view(scan, scan.views[0])  # reconstruct_scan's points, in memory (no PLY round trip)
        ev = evaluate_view(scan, "view_000", cloud.points, sigma=cloud.sigma)
        out[name] = (ev["median_mm"], cloud.stats["points"])
    return out


def test_crossings_do_not_depend_on_the_light_gamma_or_its_compensation(medians):
    print(json.dumps(medians))
    lin, n_lin = medians["linear"]
    for name in ("precompensated", "plain"):
        med, n = medians[name]
        assert abs(med / lin - 1.0) <= 0.10, (name, med, lin)
        assert abs(n / n_lin - 1.0) <= 0.05, (name, n, n_lin)


@pytest.mark.parametrize("blur,least,most", [(0.0, 0.0, 0.0), (6.0, 0.5, 1.0)])
def test_a_finest_bit_that_barely_modulates_is_counted_and_its_own_edges_are_not(blur, least, most):
    """Sharp frames: every weak finest bit is on one of that bit's edges (none counted). Blurred by
    6 px, the finest bit (a 16 px period at pitch 4: its modulation ~6 % of white, below the 12 %
    margin) washes out over most of the frame while the coarsest (64 px) holds: most lit pixels count."""
    import warp as wp

    from ringscan.kernels.ring_labels import decode_gray_rings
    from ringscan.pipeline.codecs.gray_rings import low_modulation_pixels
    from tests.support.ring_frames import frame_stack, gray_rings_spec

    spec = gray_rings_spec()
    labels = decode_gray_rings(wp.array(frame_stack(spec, blur=blur), device="cpu"), bits=spec.bits,
                               sector_bits=spec.sector_bits)
    low, lit = low_modulation_pixels(labels, bits=spec.bits, min_contrast=12.0)
    assert lit == spec.width * spec.height  # every pixel of a frame drawn straight from the pattern is lit
    assert least * lit <= low <= most * lit


def test_a_view_whose_finest_bit_washes_out_says_so_in_one_line(tmp_path, caplog):
    """A projector defocused by 6 px on crop_rig (pitch 2: the finest bit's 8 px period is gone): the
    view counts its low_modulation pixels and warns once with their share; in focus, it does not."""
    import logging

    from ringscan.pipeline.simulate.virtual_rig import RenderSettings

    counts = {}
    for name, defocus in (("focused", 0.7), ("defocused", 6.0)):
        scan = simulate_scan(tmp_path / name, scene="sphere", rig=crop_rig(), patterns=parse_patterns(GRAY),
                             settings=RenderSettings(defocus_px=defocus), progress=False)
        caplog.clear()
        with caplog.at_level(logging.WARNING, logger="ringscan.pipeline.reconstruct.view"):
            cloud = reconstruct_view(scan, scan.views[0])
        lines = [r.getMessage() for r in caplog.records if "low_modulation" in r.getMessage()]
        counts[name] = (cloud.stats["low_modulation"] / cloud.stats["pixels_lit"], lines)
    share, lines = counts["defocused"]
    assert share > 0.05 and len(lines) == 1 and f"{100 * share:.0f} %" in lines[0]
    share, lines = counts["focused"]
    assert share < 0.05 and not lines


def test_a_noisier_part_of_the_view_gets_wider_sigmas_than_the_rest(tmp_path):
    """A view whose right quarter's frames carry 6 levels more noise (independently in every frame, as a
    noisier part of a camera's image, or Monte Carlo light, does): there each sample's sigma of rho grows
    by its measured noise over the view's median (~4x: the rendered noise is 1.5 levels); elsewhere it
    stays as the decode's model put it (the view's median is the quiet part's noise). The view reports
    the noise it measured."""
    import numpy as np
    import warp as wp

    from ringscan.pipeline.codecs.registry import codec_for
    from ringscan.pipeline.formats.scan import read_view_frames
    from ringscan.pipeline.reconstruct.settings import ReconstructSettings

    scan = simulate_scan(tmp_path / "s", scene="sphere", rig=crop_rig(), patterns=parse_patterns(GRAY), progress=False)
    view = scan.views[0]
    clean = read_view_frames(scan, view)
    w = clean.shape[2]
    rng = np.random.default_rng(7)
    noisy = clean.astype(np.float64)
    noisy[:, :, 3 * w // 4:] += rng.normal(0.0, 6.0, noisy[:, :, 3 * w // 4:].shape)
    noisy = np.clip(np.rint(noisy), 0, 255).astype(np.uint8)
    codec = codec_for(scan.patterns.codec)
    st = codec.settings_from(ReconstructSettings())
    ratios = {}
    for tag, frames in (("clean", clean), ("noisy", noisy)):
        samples, stats = codec.extract(wp.array(frames, device="cpu"), scan, st, threads=1)
        u = samples.uv.numpy()[:, 0]
        s = samples.sigma_rho.numpy()
        ratios[tag] = (np.median(s[u >= 3 * w // 4 + 3]), np.median(s[u < 3 * w // 4 - 3]), stats["frame_noise"])
    (loud_c, quiet_c, noise_c), (loud_n, quiet_n, noise_n) = ratios["clean"], ratios["noisy"]
    assert loud_n / loud_c > 2.5  # sqrt(1.5^2 + 6^2) / ~1.5-2 levels
    assert quiet_n / quiet_c == pytest.approx(1.0, abs=0.1)  # the quiet part's own scatter about the median
    assert noise_n["p90_levels"] > 2.5 * noise_n["median_levels"]  # the loud quarter is the top fourth
    assert noise_c["p90_levels"] < 1.5 * noise_c["median_levels"]


def test_a_camera_that_spreads_each_projector_pixel_over_several_keeps_its_ring_edges(tmp_path, monkeypatch):
    """crop_rig's camera zoomed 4x (a projector px over ~3.4 camera px: a high-resolution camera, or a close
    one): an edge's step between two neighbouring pixels is ~3.4x flatter at the same sharpness against the
    band, and the sampler's min_slope (per camera px) had dropped nearly every edge (3x: 1.4 % of them, 4x and
    more: none, ``no ring edge was sampled``). Taken per projector px (``projector_px_span``), the edges are
    sampled, at the accuracy of the unzoomed camera's, and their sigmas hold."""
    import numpy as np
    import warp as wp

    import ringscan.pipeline.codecs.gray_rings as gr
    from ringscan.pipeline.geometry import projector_px_span
    from ringscan.pipeline.codecs.registry import codec_for
    from ringscan.pipeline.formats.scan import read_view_frames
    from ringscan.pipeline.reconstruct.settings import ReconstructSettings

    rig = crop_rig(width=160, height=128)
    K = rig.camera.K.copy()
    K[0, 0] *= 4
    K[1, 1] *= 4
    rig = dataclasses.replace(rig, camera=dataclasses.replace(rig.camera, K=K))
    span = projector_px_span(rig)
    assert 3.0 < span < 4.0 and projector_px_span(crop_rig()) < 1.0  # (unzoomed: no change)
    scan = simulate_scan(tmp_path / "s", scene="sphere", rig=rig, patterns=parse_patterns(GRAY), progress=False)
    cloud = reconstruct_view(scan, scan.views[0])
    ev = evaluate_view(scan, "view_000", cloud.points, sigma=cloud.sigma)
    assert len(cloud.points) > 1000 and ev["coverage"] > 0.9, (len(cloud.points), ev["coverage"])  # (~23 rings across)
    assert ev["median_mm"] < 0.01 and 0.4 < ev["sigma"]["median_ratio"] < 1.2
    # the same frames with min_slope per camera px, as before
    monkeypatch.setattr(gr, "MIN_OVERSAMPLING", np.inf)
    frames = wp.array(read_view_frames(scan, scan.views[0]), dtype=wp.uint8, device="cpu")
    settings = codec_for(scan.patterns.codec).settings_from(ReconstructSettings())
    samples, _ = gr.extract_gray_rings(frames, scan, settings, threads=2)
    assert len(samples) < 0.1 * len(cloud.points)


def test_a_camera_too_coarse_for_the_angle_code_says_which_period_it_needs(tmp_path, caplog):
    """The default rig's camera at a quarter of its resolution (a projector px over ~0.21 camera px: a camera
    far coarser than the projector) under the default patterns: the angle's least period (8 projector px) spans
    ~1.7 camera px, where its fringes fade or alias (ringscan's sharp render: ~11 % of the points beyond 3 sigma,
    each off by a fraction of a period). The view warns with the period this camera needs, and the patterns it
    advises (``--angle-period 16``) hold the sigmas' bounds (issue 32's) on the same rig, more accurately."""
    import logging

    import numpy as np

    from ringscan.pipeline.codecs import angle_code
    from ringscan.pipeline.formats.rig import default_rig
    from ringscan.pipeline.geometry import projector_px_span

    rig = default_rig(light_model="perspective")
    K = rig.camera.K.copy()
    K[:2] *= 0.25
    rig = dataclasses.replace(rig, camera=dataclasses.replace(rig.camera, width=320, height=256, K=K))
    span = projector_px_span(rig)
    assert 0.15 < span < 0.3
    spec = {"codec": "gray-rings", "width": 1024, "height": 768, "center": [511.5, 383.5], "rho0": 8.0, "pitch": 4.0,
            "bits": 7, "sector_bits": 9, "angle_steps": 4, "angle_period": 8.0}
    need = angle_code.MIN_PERIOD_CAMERA_PX / span  # ~12 projector px; advised a third more: 16
    advice = int(4 * np.ceil(1.3 * need / 4))
    assert advice == 16
    figures = {}
    for period in (8.0, 16.0):
        scan = simulate_scan(tmp_path / f"s{period:.0f}", scene="sphere", rig=rig,
                             patterns=parse_patterns({**spec, "angle_period": period}), progress=False)
        caplog.clear()
        with caplog.at_level(logging.WARNING):
            cloud = reconstruct_view(scan, scan.views[0])
        warned = [r.message for r in caplog.records if "--angle-period" in r.message]
        figures[period] = (evaluate_view(scan, "view_000", cloud.points, sigma=cloud.sigma), warned)
    ev8, warned8 = figures[8.0]
    ev16, warned16 = figures[16.0]
    assert len(warned8) == 1 and f"--angle-period {advice}" in warned8[0] and not warned16
    assert ev16["coverage"] > 0.9 and 0.4 < ev16["sigma"]["median_ratio"] < 1.2 and ev16["sigma"]["beyond_3"] <= 0.05
    assert ev16["median_mm"] < ev8["median_mm"] and ev8["sigma"]["beyond_3"] > 0.05  # (what the warning is for)
