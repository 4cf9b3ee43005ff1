"""Reconstruction settings from a file, --set and --min-confidence: checked against
their types with the field's path named; the points min_confidence removes counted."""

from __future__ import annotations

import json

import numpy as np
import pytest

from ringscan.pipeline.formats.ply import read_ply
from ringscan.pipeline.formats.settings import settings_json_schema
from ringscan.pipeline.reconstruct import reconstruct_scan
from ringscan.pipeline.reconstruct.settings import ReconstructSettings
from ringscan.tools.cli import main
from tests.pipeline.reconstruct.tiny_scan import simulate_tiny_scan


@pytest.fixture(scope="module")
def tiny_scan(tmp_path_factory):
    return simulate_tiny_scan(tmp_path_factory.mktemp("scan") / "scan").folder


@pytest.mark.parametrize("settings, message", [
    ({"min_confidence": "high"}, "min_confidence: expected a number, got 'high'"),
    ({"decode": {"min_contrast": [1]}}, "decode.min_contrast: expected a number, got [1]"),
    ({"threads": 1.5}, "threads: expected a whole number, got 1.5"),
    ({"phase": {"weighted": "yes"}}, "phase.weighted: expected true or false, got 'yes'"),
    ({"triangulate": 3}, "triangulate: expected an object of settings, got 3"),
    ({"triangulate": {"margin": 0.3}}, "triangulate.margin: unknown setting of TriangulateSettings"),
    ({"min_confidence": 1.5}, "min_confidence: expected a confidence in 0..1, got 1.5"),
])
def test_a_settings_file_of_the_wrong_type_is_one_line_naming_the_field(tiny_scan, tmp_path, capsys, settings,
                                                                         message):
    path = tmp_path / "s.json"
    path.write_text(json.dumps(settings))
    out = tmp_path / "out"
    assert main(["reconstruct", str(tiny_scan), "--out", str(out), "--settings", str(path), "--device", "cpu"]) == 1
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "Traceback" not in err, err
    assert err.startswith(f"ringscan reconstruct: error: {path}: {message}"), err
    assert not out.exists()


def test_set_and_min_confidence_flags_are_usage_errors_when_wrong(tiny_scan, tmp_path, capsys):
    out = str(tmp_path / "out")
    assert main(["reconstruct", str(tiny_scan), "--out", out, "--set", "decode.min_contrast=abc"]) == 2
    assert "--set: decode.min_contrast: expected a number, got 'abc'" in capsys.readouterr().err
    assert main(["reconstruct", str(tiny_scan), "--out", out, "--set", "min_contrast"]) == 2
    assert "expected KEY=VALUE" in capsys.readouterr().err
    assert main(["reconstruct", str(tiny_scan), "--out", out, "--min-confidence", "2"]) == 2
    assert "--min-confidence: expected a confidence in 0..1, got 2.0" in capsys.readouterr().err


def test_library_settings_of_the_wrong_type_are_refused_before_any_kernel(tiny_scan, tmp_path):
    with pytest.raises(ValueError, match=r"ReconstructSettings.min_confidence: expected a number, got 'high'"):
        reconstruct_scan(tiny_scan, tmp_path / "out", settings=ReconstructSettings(min_confidence="high"),
                         device="cpu", progress=False)
    assert not (tmp_path / "out").exists()


def test_min_confidence_drops_are_counted(tiny_scan, tmp_path, capsys):
    full, cut = tmp_path / "full", tmp_path / "cut"
    assert main(["reconstruct", str(tiny_scan), "--out", str(full), "--device", "cpu", "--no-progress"]) == 0
    conf = read_ply(full / "view_000.ply")["confidence"]
    c = float(np.median(conf))  # about half the points fall below it
    assert main(["reconstruct", str(tiny_scan), "--out", str(cut), "--device", "cpu", "--no-progress",
                 "--set", "decode.min_contrast=12", "--min-confidence", str(c)]) == 0
    rep_full = json.loads((full / "report.json").read_text())
    rep_cut = json.loads((cut / "report.json").read_text())
    below = int(np.count_nonzero(conf < c))
    assert below > 0
    assert rep_full["totals"]["dropped"]["low_confidence"] == 0
    assert rep_cut["totals"]["dropped"]["low_confidence"] == below
    assert rep_cut["totals"]["points"] == rep_full["totals"]["points"] - below
    assert rep_cut["settings"]["min_confidence"] == c and rep_cut["settings"]["decode"]["min_contrast"] == 12
    # every sample is either a point or counted by a reason
    tot = rep_cut["totals"]
    assert tot["points"] + sum(tot["dropped"].values()) == tot["samples"]


def test_settings_schema_describes_every_field():
    schema = settings_json_schema(ReconstructSettings)
    props = schema["properties"]
    assert props["min_confidence"]["type"] == "number"
    assert props["min_confidence"]["description"] == "Points below this confidence are not written."
    assert props["threads"]["type"] == "integer"
    assert schema["$defs"]["DecodeSettings"]["properties"]["min_contrast"]["description"].startswith("Least white")
