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
from tests.support.tiny_scan import simulate_tiny_scan


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
    ({"single_shot": {"fork_px": 2.0}}, "single_shot.fork_px: no longer a setting (fixed at 0.9)"),
    ({"stereo": {"match": {"line_ratio": 0.05}}}, "stereo.match.line_ratio: no longer a setting (fixed at 0.02)"),
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


def test_an_old_settings_file_naming_retired_fields_at_their_fixed_values_still_loads():
    """The single-shot labeller's thresholds became fixed (``LabelTuning``); a run's
    settings.json from before names each with the value it is fixed at."""
    from ringscan.pipeline.codecs.single_shot.settings import TUNING, LabelTuning
    from ringscan.pipeline.formats.settings import settings_from_dict
    import dataclasses

    old = {f.name: getattr(TUNING, f.name) for f in dataclasses.fields(LabelTuning)}
    assert len(old) == 18
    s = settings_from_dict(ReconstructSettings, {"single_shot": {**old, "min_piece_samples": 20,
                                                                 "lines": {"confidence_contrast": 40.0}},
                                                 "stereo": {"match": {"line_ratio": 0.02}}})
    assert s.single_shot.min_piece_samples == 20
    assert s == ReconstructSettings(single_shot=dataclasses.replace(ReconstructSettings().single_shot,
                                                                    min_piece_samples=20))


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


def _numeric_settings(s, prefix=""):
    """The paths of every numeric setting (ints and floats, not booleans) of a settings dataclass."""
    import dataclasses

    for f in dataclasses.fields(s):
        v = getattr(s, f.name)
        if dataclasses.is_dataclass(v):
            yield from _numeric_settings(v, f"{prefix}{f.name}.")
        elif isinstance(v, (int, float)) and not isinstance(v, bool):
            yield f"{prefix}{f.name}"


def test_every_numeric_setting_has_a_range_with_a_reason():
    from ringscan.pipeline.reconstruct.settings import SETTING_RANGES, check_setting_ranges

    assert set(SETTING_RANGES) == set(_numeric_settings(ReconstructSettings()))
    assert all(len(b.why) > 8 and b.lo <= b.hi for b in SETTING_RANGES.values())
    check_setting_ranges(ReconstructSettings())  # the defaults lie inside


@pytest.mark.parametrize("assignment, message", [
    ("decode.min_contrast=1e308", "decode.min_contrast: 1e+308 is outside 1 .. 200 (8-bit grey levels"),
    ("decode.min_contrast=255", "decode.min_contrast: 255 is outside 1 .. 200"),
    ("decode.min_contrast=1e20", "decode.min_contrast: 1e+20 is outside 1 .. 200"),
    ("decode.min_contrast=-5", "decode.min_contrast: -5 is outside 1 .. 200"),
    ("filter.radius=-1", "filter.radius: -1 is outside 0 .. 8 (pixels: 0 turns the filter off"),
    ("threads=-1", "threads: -1 is outside 0 .. 4096 (CPU threads"),
    ("stereo.match.cell_px=1e-9", "stereo.match.cell_px: 1e-09 is outside 1 .. 1024 (projector px"),
    ("filter.min_neighbours=30", "filter.min_neighbours: 30 is more than the window of radius 2 holds (24)"),
])
def test_a_setting_outside_its_range_is_refused_before_anything_is_written(tiny_scan, tmp_path, capsys,
                                                                           assignment, message):
    out = tmp_path / "out"
    assert main(["reconstruct", str(tiny_scan), "--out", str(out), "--set", assignment, "--device", "cpu",
                 "--no-progress"]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "Traceback" not in err, err
    assert err.startswith(f"ringscan reconstruct: error: --set: {message}"), err
    assert not out.exists()


def test_a_settings_file_outside_the_range_names_the_file_and_batch_refuses_it_too(tiny_scan, tmp_path, capsys):
    path = tmp_path / "s.json"
    path.write_text(json.dumps({"filter": {"radius": -1}}))
    for command in ("reconstruct", "batch"):
        out = tmp_path / command
        assert main([command, str(tiny_scan), "--out", str(out), "--settings", str(path), "--device", "cpu",
                     "--no-progress"]) == 1
        err = capsys.readouterr().err.strip()
        assert err == (f"ringscan {command}: error: {path}: filter.radius: -1 is outside 0 .. 8 (pixels: 0 turns "
                       "the filter off; above 8 the window (17x17) reaches past a ring's neighbours and costs "
                       "(2r+1)^2 tests a point)"), err
        assert not out.exists()


def test_library_settings_out_of_range_are_refused_by_reconstruct_and_batch(tiny_scan, tmp_path):
    import dataclasses

    from ringscan.pipeline.batch import batch_reconstruct

    bad = ReconstructSettings(decode=dataclasses.replace(ReconstructSettings().decode, min_contrast=1e308))
    with pytest.raises(ValueError, match=r"^decode.min_contrast: 1e\+308 is outside 1 .. 200"):
        reconstruct_scan(tiny_scan, tmp_path / "out", settings=bad, device="cpu", progress=False)
    with pytest.raises(ValueError, match=r"^decode.min_contrast: 1e\+308 is outside 1 .. 200"):
        batch_reconstruct(tiny_scan, tmp_path / "batch", settings=bad, device="cpu", workers=0, progress=False)
    assert not (tmp_path / "out").exists() and not (tmp_path / "batch").exists()


def test_no_pixel_decoded_writes_no_point(tiny_scan, tmp_path, capsys):
    """decode.min_contrast 200 (in range) decodes no pixel of the tiny scan (white - black is below 200
    everywhere); the sampler still finds edges (sample.min_contrast 12), which before gave 16 points of rings
    no band label confirmed, none with a sector."""
    out = tmp_path / "out"
    assert main(["reconstruct", str(tiny_scan), "--out", str(out), "--set", "decode.min_contrast=200",
                 "--device", "cpu", "--no-progress"]) == 1
    err = capsys.readouterr().err
    assert "ringscan reconstruct: error: no view of" in err and "below 200 grey levels at every pixel" in err
    rep = json.loads((out / "report.json").read_text())
    assert rep["totals"]["pixels_decoded"] == 0
    assert rep["totals"]["points"] == 0 and rep["totals"]["samples"] == 0
    assert len(read_ply(out / "view_000.ply")["x"]) == 0
