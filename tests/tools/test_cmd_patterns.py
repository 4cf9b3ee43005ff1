"""``ringscan patterns --rig``: frames pre-compensated for the rig's light gamma, the gamma in
patterns.json, and a capture of those patterns carrying it in scan.json."""

import dataclasses

import numpy as np

from ringscan.pipeline.codecs.render import render_frame
from ringscan.pipeline.formats.atomic import read_json
from ringscan.pipeline.formats.images import read_image
from ringscan.pipeline.formats.patterns import parse_patterns
from ringscan.pipeline.formats.rig import save_rig
from ringscan.pipeline.formats.scan import load_scan
from ringscan.tools.cli import main
from tests.support.hardware_rig import small_rig

PAT = ["--codec", "phase-rings", "--bits", "2", "--sector-bits", "0", "--pitch", "40", "--steps", "3"]


def _rig(tmp_path, light_gamma):
    rig = small_rig()
    rig = dataclasses.replace(rig, light=dataclasses.replace(rig.light, gamma=light_gamma))
    save_rig(tmp_path / "rig.json", rig)
    return tmp_path / "rig.json"


def test_patterns_rig_precompensates(tmp_path, capsys):
    rig = _rig(tmp_path, 2.2)
    assert main(["patterns", *PAT, "--rig", str(rig), "--out", str(tmp_path / "pat")]) == 0
    assert "pre-compensated for a light gamma of 2.2" in capsys.readouterr().out
    d = read_json(tmp_path / "pat" / "patterns.json")
    assert d["precompensated_gamma"] == 2.2 and (d["width"], d["height"]) == (1024, 768)
    plain = parse_patterns({k: v for k, v in d.items() if k != "precompensated_gamma"})
    lin = render_frame(plain, "phase_0") / 255.0
    pre = read_image(tmp_path / "pat" / "phase_0.png") / 255.0
    # the light of gamma 2.2 emits the meant fringe (to the 8-bit rounding)
    assert np.max(np.abs(pre ** 2.2 - lin)) <= 1.6 / 255.0
    np.testing.assert_array_equal(read_image(tmp_path / "pat" / "white.png"), render_frame(plain, "white"))
    # --precompensate by hand gives the same frames; --rig with it, or another size, is refused
    assert main(["patterns", *PAT, "--precompensate", "2.2", "--out", str(tmp_path / "pat2")]) == 0
    np.testing.assert_array_equal(read_image(tmp_path / "pat2" / "phase_0.png"),
                                  read_image(tmp_path / "pat" / "phase_0.png"))
    capsys.readouterr()
    assert main(["patterns", *PAT, "--rig", str(rig), "--precompensate", "2", "--out", str(tmp_path / "x")]) == 2
    assert "not both" in capsys.readouterr().err
    assert main(["patterns", *PAT, "--rig", str(rig), "--width", "800", "--out", str(tmp_path / "x")]) == 2
    assert "differ from the projector" in capsys.readouterr().err
    assert main(["patterns", *PAT, "--precompensate", "0", "--out", str(tmp_path / "x")]) == 1
    assert "patterns.precompensated_gamma: must be > 0" in capsys.readouterr().err


def test_linear_rig_writes_plain_frames(tmp_path):
    assert main(["patterns", *PAT, "--rig", str(_rig(tmp_path, 1.0)), "--out", str(tmp_path / "pat")]) == 0
    assert "precompensated_gamma" not in read_json(tmp_path / "pat" / "patterns.json")


def test_capture_carries_the_precompensation(tmp_path):
    """A virtual capture of pre-compensated patterns stores them in scan.json, so the
    decoder of that scan knows."""
    rig = _rig(tmp_path, 2.2)
    assert main(["patterns", "--codec", "gray-rings", "--bits", "2", "--sector-bits", "0", "--pitch", "40",
                 "--rig", str(rig), "--out", str(tmp_path / "pat")]) == 0
    assert main(["capture", "--rig", str(rig), "--patterns", str(tmp_path / "pat" / "patterns.json"), "--views", "1",
                 "--out", str(tmp_path / "scan"), "--no-progress", "--virtual", "terrain", "--device", "cpu"]) == 0
    scan = load_scan(tmp_path / "scan")
    assert scan.patterns.precompensated_gamma == 2.2
    assert read_json(tmp_path / "scan" / "scan.json")["patterns"]["precompensated_gamma"] == 2.2


def test_every_codec_parameter_is_a_pattern_option():
    """The codec options of ``patterns``/``simulate`` come from ``formats.patterns.pattern_options``
    (the one place on the command line that names the codecs): one option a parameter of
    every projectable codec, each a ``default_patterns`` keyword."""
    import argparse

    from ringscan.pipeline.codecs import DEFAULT_CODEC
    from ringscan.pipeline.formats.patterns import CODECS, PATTERN_LAYOUTS, pattern_options
    from ringscan.tools.cmd_patterns import add_pattern_options

    dests = [o.dest for o in pattern_options()]
    params = {p.name for c in CODECS for p in PATTERN_LAYOUTS[c].parameters}
    assert len(dests) == len(set(dests)) and set(dests) == params | {"rho0", "pitch"}
    p = argparse.ArgumentParser()
    add_pattern_options(p)
    args = p.parse_args([])
    assert args.codec == DEFAULT_CODEC in CODECS and all(getattr(args, d) is None for d in dests)
