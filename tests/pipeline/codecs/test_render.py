"""Projector frames pre-compensated for the light's gamma (patterns.precompensated_gamma):
a light of that gamma emits the light the linear pattern means; binary levels are unchanged."""

import dataclasses

import numpy as np
import pytest

from ringscan.pipeline.codecs.render import render_frame
from ringscan.pipeline.formats.patterns import frame_names, parse_patterns

G = 2.2
SPECS = {
    "phase-rings": {"codec": "phase-rings", "width": 96, "height": 72, "center": [47.3, 35.8], "rho0": 3.0,
                    "pitch": 5.0, "bits": 3, "sector_bits": 2, "steps": 4},
    "gray-rings": {"codec": "gray-rings", "width": 96, "height": 72, "center": [47.3, 35.8], "rho0": 3.0,
                   "pitch": 2.5, "bits": 4, "sector_bits": 3},
    "rings": {"codec": "rings", "width": 96, "height": 72, "center": [47.3, 35.8], "rho0": 6.0, "pitch": 6.0,
              "count": 5, "line_width": 2.5},
}


@pytest.mark.parametrize("codec", list(SPECS))
def test_light_of_that_gamma_emits_the_meant_light(codec):
    lin_spec = parse_patterns(SPECS[codec])
    pre_spec = dataclasses.replace(lin_spec, precompensated_gamma=G)
    for name in frame_names(lin_spec):
        lin = render_frame(lin_spec, name)
        pre = render_frame(pre_spec, name)
        meant = lin / 255.0  # the light the pattern means (to half an 8-bit step)
        emitted = (pre / 255.0) ** G
        # rounding of the compensated value: at most half a step times d(x^G)/dx <= G / 255
        assert np.max(np.abs(emitted - meant)) <= (0.5 + 0.5 * G) / 255.0 + 1e-9, name
        ends = (lin == 0) | (lin == 255)
        if name in ("white", "black"):
            np.testing.assert_array_equal(pre, lin)
        if name.startswith("gray"):
            # binary bands are unchanged more than half a pixel (radially) from every band edge
            v, u = np.mgrid[0:lin_spec.height, 0:lin_spec.width]
            rho = np.hypot(u - lin_spec.center[0], v - lin_spec.center[1])
            edges = lin_spec.rho0 + lin_spec.pitch * np.arange(lin_spec.n_bands + 1)
            away = np.min(np.abs(rho[..., None] - edges), axis=-1) > 0.5
            assert np.all(np.isin(lin[away], (0, 255)))
            np.testing.assert_array_equal(pre[away], lin[away])
        grey = ~ends
        if grey.any():
            assert np.all(pre[grey] >= lin[grey])  # v^(1/G) >= v on [0, 1]
            # without pre-compensation the same light would be far from the meant one
            if name not in ("white", "black"):
                assert np.max(np.abs(meant ** G - meant)) > 0.05, name


def test_frame_and_inverse_still_cross_where_both_emit_half():
    """The pair's edges are symmetric: a pixel's frame and inverse light add up to full
    light after pre-compensation, so they cross where each is half (as in the linear case)."""
    spec = dataclasses.replace(parse_patterns(SPECS["gray-rings"]), precompensated_gamma=G)
    lin_spec = parse_patterns(SPECS["gray-rings"])
    for b in range(spec.bits):
        f = (render_frame(spec, f"gray_{b}") / 255.0) ** G
        inv = (render_frame(spec, f"gray_{b}_inv") / 255.0) ** G
        inside = (render_frame(lin_spec, "gray_0").astype(int) + render_frame(lin_spec, "gray_0_inv")) >= 254
        assert np.max(np.abs((f + inv)[inside] - 1.0)) <= (1.0 + G) / 255.0
        # the sign of frame - inverse (which side of the crossing) is that of the linear pair
        lf, li = render_frame(lin_spec, f"gray_{b}").astype(int), render_frame(lin_spec, f"gray_{b}_inv").astype(int)
        clear = np.abs(lf - li) >= 3
        assert np.array_equal(np.sign(f - inv)[clear], np.sign(lf - li)[clear])
