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
