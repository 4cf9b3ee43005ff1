"""patterns.precompensated_gamma: parsed, validated and written back like the other fields; the
default angle code's zones."""

import json

import numpy as np
import pytest

from ringscan.pipeline.formats.errors import FormatError
from ringscan.pipeline.formats.patterns import angle_periods, default_patterns, parse_patterns, spec_angle_zones

BASE = {"codec": "phase-rings", "width": 64, "height": 48, "center": [31.5, 23.5], "rho0": 2.0, "pitch": 4.0,
        "bits": 3, "sector_bits": 0, "steps": 4}


def test_precompensated_gamma_round_trips_and_defaults_to_none():
    spec = parse_patterns({**BASE, "precompensated_gamma": 2.2})
    assert spec.precompensated_gamma == 2.2
    d = spec.to_dict()
    assert d["precompensated_gamma"] == 2.2
    assert parse_patterns(json.loads(json.dumps(d))) == spec
    plain = parse_patterns(BASE)
    assert plain.precompensated_gamma == 1.0
    assert "precompensated_gamma" not in plain.to_dict()  # scan.json of uncompensated scans is unchanged
    assert default_patterns("gray-rings", precompensated_gamma=1.8).precompensated_gamma == 1.8
    assert default_patterns("rings", precompensated_gamma=1.8).to_dict()["precompensated_gamma"] == 1.8


@pytest.mark.parametrize("value,message", [("2.2", "finite number"), (True, "finite number"), (0, "> 0"),
                                           (-1.0, "> 0"), (11.0, r"\[0.1, 10\]"), (None, "finite number")])
def test_bad_precompensated_gamma_names_file_and_field(value, message):
    with pytest.raises(FormatError, match=rf"scan\.json.*patterns\.precompensated_gamma.*{message}"):
        parse_patterns({**BASE, "precompensated_gamma": value}, source="scan.json")


def test_imported_codec_has_no_precompensation():
    dec = {"codec": "decoded", "width": 64, "height": 48, "center": [31.5, 60.0], "rho0": 0.0, "pitch": 1.0}
    assert parse_patterns(dec).precompensated_gamma == 1.0
    with pytest.raises(FormatError, match="precompensated_gamma: not for the decoded codec"):
        parse_patterns({**dec, "precompensated_gamma": 2.2}, source="scan.json")


def test_default_angle_code_stays_sharp_out_to_the_rim():
    """The default angle code of gray-rings and phase-rings: every period resolvable (>= angle_period),
    unwrappable by the sector code (P <= 2^(S-1)), and at the annulus's outer radius no longer than
    2 x angle_period, i.e. the number of periods is not capped by the sector bits before the rim (with 8 sector
    bits it was: 25.5 px at rho 520)."""
    for codec in ("gray-rings", "phase-rings"):
        _check_sharp_to_the_rim(default_patterns(codec))


def _check_sharp_to_the_rim(spec):
    starts, periods = spec_angle_zones(spec)
    assert periods.max() <= 2 ** (spec.sector_bits - 1)
    outer = spec.rho0 + spec.n_bands * spec.pitch
    rho = np.linspace(spec.rho0, outer, 4000)
    period = 2 * np.pi * rho / angle_periods(rho, starts, periods)
    assert period.min() >= spec.angle_period - 1e-6
    assert period[-1] <= 2 * spec.angle_period
