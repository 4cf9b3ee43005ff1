"""The conditioning map: where rings alone are blind, the angle is not, and both
place (nearly) every lit pixel, against the geometry of the rig itself."""

import json

import numpy as np
import pytest

from ringscan.pipeline.evaluate.conditioning import ConditioningSettings, compute_conditioning, plot_conditioning
from ringscan.pipeline.formats.rig import default_rig, load_rig


def test_default_rig_rings_have_blind_spots_both_do_not(tmp_path):
    rig = default_rig(light_model="perspective")
    cm = compute_conditioning(rig, center=(511.5, 383.5), rho_range=(8, 520), sector_bits=6,
                              settings=ConditioningSettings(step=8), device="cpu")
    s = cm.summary()
    assert cm.lit.mean() > 0.2
    assert s["rings"]["placed"] < 0.99  # the grazing gaps of the ring constraint
    assert s["both"]["placed"] > 0.999
    # both is never worse than either alone where that one places the point
    for k in ("rings", "angle"):
        m = np.isfinite(cm.sigma[k]) & np.isfinite(cm.sigma["both"])
        assert np.all(cm.sigma["both"][m] <= cm.sigma[k][m] * 1.001 + 1e-6)
    out = plot_conditioning(cm, tmp_path / "c.png", title="default")
    assert out.stat().st_size > 10_000
    assert plot_conditioning(cm, tmp_path / "c.svg").read_text().startswith("<?xml")


def test_oblique_rig_band(shared_data):
    rig = load_rig(shared_data / "rigs" / "oblique_projector.json")
    li = rig.light
    cm = compute_conditioning(rig, center=(li.K[0, 2], li.K[1, 2]), rho_range=(0, 2000), sector_bits=6,
                              settings=ConditioningSettings(step=16), device="cpu")
    s = cm.summary()
    assert s["rings"]["placed"] < 0.95 and s["both"]["placed"] > 0.99
    json.dumps(s)


def test_bad_settings():
    with pytest.raises(ValueError, match="step"):
        compute_conditioning(default_rig(), center=(0, 0), rho_range=(0, 10), settings=ConditioningSettings(step=0))
