"""The codec registry: a codec module that fails to import surfaces as its own
ImportError (never as "no reconstruction for codec"), an unknown codec is a
clear FormatError naming the scan, and a run loads only its own codec's module."""

import dataclasses
import json
import os
import subprocess
import sys
import textwrap

import numpy as np
import pytest
import warp as wp

from ringscan.pipeline.codecs.registry import CODEC_CLASSES, all_codecs, extract_samples
from ringscan.pipeline.formats.errors import FormatError
from ringscan.pipeline.formats.patterns import CODECS, IMPORTED_CODECS, PATTERN_LAYOUTS, parse_patterns
from ringscan.pipeline.formats.rig import default_rig
from ringscan.pipeline.formats.scan import read_view_frames
from ringscan.pipeline.reconstruct.settings import ReconstructSettings
from ringscan.pipeline.simulate.scan import simulate_scan
from ringscan.tools.cli import main

# A meta-path hook that makes one module fail to import the way a broken install
# does (a shared library that will not load), without touching the checkout.
BREAK = textwrap.dedent("""
    import importlib.abc, sys

    class Broken(importlib.abc.MetaPathFinder):
        def find_spec(self, name, path=None, target=None):
            if name == {target!r}:
                raise ImportError("libcodec_test.so: cannot open shared object file (simulated)")
            return None

    sys.meta_path.insert(0, Broken())
""")


def _run_broken(target: str, body: str) -> subprocess.CompletedProcess:
    code = BREAK.format(target=target) + textwrap.dedent(body)
    env = {**os.environ, "PYTHONDONTWRITEBYTECODE": "1"}
    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, env=env)


@pytest.mark.parametrize("target, codec, codec_module", [
    ("ringscan.kernels.phase", "phase-rings", "codecs/phase_rings.py"),
    ("ringscan.pipeline.codecs.single_shot.labeller", "rings", "single_shot"),
])
def test_import_failure_in_a_codec_surfaces_as_itself(target, codec, codec_module):
    r = _run_broken(target, f"from ringscan.pipeline.codecs.registry import codec_for\ncodec_for({codec!r})\n")
    assert r.returncode != 0
    assert "ImportError: libcodec_test.so: cannot open shared object file (simulated)" in r.stderr
    assert codec_module in r.stderr          # the traceback runs through the codec module
    assert "no reconstruction for codec" not in r.stderr + r.stdout


def test_import_failure_reaches_the_command_line_as_itself(small_scan, tmp_path):
    """``ringscan reconstruct`` of a scan whose codec's module cannot load: the user sees
    the import error (what to fix), not a claim that the codec is not built in."""
    r = _run_broken("ringscan.kernels.ring_labels", f"""
        from ringscan.tools.cli import main
        raise SystemExit(main(["reconstruct", {str(small_scan.folder)!r}, "--out", {str(tmp_path / 'out')!r}]))
    """)
    assert r.returncode != 0
    assert "libcodec_test.so: cannot open shared object file (simulated)" in r.stderr
    assert "no reconstruction for codec" not in r.stderr + r.stdout


def test_every_known_codec_has_a_reconstruction():
    assert set(CODEC_CLASSES) == set(CODECS) | set(IMPORTED_CODECS)
    for name, codec in all_codecs().items():
        assert codec.name == name and codec.layout is PATTERN_LAYOUTS[name]


def test_only_an_imported_map_says_its_code_errs_alike_both_ways():
    """Two cameras matched camera to camera take camera 1's code error through the matcher's map wherever the
    radius and the angle err differently (every projected codec: ring edges, phase-rings' fringes); an imported
    u, v map, whose polar sigmas are turns of its two alike ones, keeps the isotropic stand-in."""
    iso = {name: codec.isotropic_code_error for name, codec in all_codecs().items()}
    assert iso == {name: name in IMPORTED_CODECS for name in CODEC_CLASSES}
    assert any(iso.values()) and not all(iso.values())


def test_a_run_loads_its_own_codec_only():
    """Reading every codec's settings and reconstructing an imported capture's view load no kernel of the
    other codecs, nor the neighbour model's (views without an angle code), until they are used (Warp parses
    a module's kernels as it is imported: ~0.1 s of every command)."""
    r = subprocess.run([sys.executable, "-c", textwrap.dedent("""
        import sys
        from ringscan.pipeline.reconstruct.settings import ReconstructSettings
        from ringscan.pipeline.reconstruct.view import reconstruct_view
        from ringscan.pipeline.codecs.registry import codec_for
        ReconstructSettings()
        codec_for("decoded")
        print(sorted(m for m in sys.modules if m.startswith("ringscan.kernels.")))
    """)], capture_output=True, text=True, timeout=120, env={**os.environ, "PYTHONDONTWRITEBYTECODE": "1"})
    assert r.returncode == 0, r.stderr
    loaded = r.stdout.strip()
    for other in ("phase", "ring_labels", "ring_sampling", "angle", "ring_lines", "sample_light", "ring_checks",
                  "cross_checks"):
        assert f"'ringscan.kernels.{other}'" not in loaded, other
    assert "'ringscan.kernels.settings'" in loaded and "'ringscan.kernels.decoded_maps'" in loaded


@pytest.fixture(scope="module")
def small_scan(tmp_path_factory):
    rig = default_rig()
    cam = dataclasses.replace(rig.camera, width=160, height=128,
                              K=np.array([[325.0, 0, 79.5], [0, 325.0, 63.5], [0, 0, 1]]))
    spec = parse_patterns({"codec": "gray-rings", "width": 1024, "height": 768, "center": [511.5, 383.5],
                           "rho0": 8.0, "pitch": 16.0, "bits": 5})
    return simulate_scan(tmp_path_factory.mktemp("reg") / "scan", scene="plane", rig=dataclasses.replace(rig, camera=cam),
                         patterns=spec, progress=False, device="cpu")


def test_unknown_codec_is_a_format_error_naming_the_scan(small_scan):
    frames = wp.array(read_view_frames(small_scan, small_scan.views[0]), device="cpu")
    odd = dataclasses.replace(small_scan, patterns=dataclasses.replace(small_scan.patterns, codec="moire"))
    with pytest.raises(FormatError, match="no reconstruction for codec 'moire'") as e:
        extract_samples(frames, odd, ReconstructSettings(), 1)
    assert e.value.path == os.fspath(small_scan.path)


def test_unknown_codec_in_scan_json_is_one_clear_line(small_scan, tmp_path, capsys):
    meta = json.loads((small_scan.folder / "scan.json").read_text())
    meta["patterns"]["codec"] = "moire"
    (small_scan.folder / "scan.json").write_text(json.dumps(meta))
    try:
        assert main(["reconstruct", str(small_scan.folder), "--out", str(tmp_path / "out"), "--no-progress"]) == 1
    finally:
        meta["patterns"]["codec"] = "gray-rings"
        (small_scan.folder / "scan.json").write_text(json.dumps(meta))
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "Traceback" not in err
    assert "scan.json" in err and "unknown codec 'moire'" in err


def test_codec_capabilities_come_from_the_codec_objects():
    from ringscan.pipeline.calibrate.light import LIGHT_CODECS
    from ringscan.pipeline.codecs.registry import codec_for

    # the single-shot labeller reads the rig's geometry, decoded captures are not projected
    assert LIGHT_CODECS == ("gray-rings", "phase-rings")
    spec = parse_patterns({"codec": "decoded", "width": 64, "height": 48, "center": [31.5, 100.0], "rho0": 0.0,
                           "pitch": 1.0})
    assert codec_for("decoded").frame_names(spec) == ["proj_u", "proj_v", "contrast"]
    with pytest.raises(ValueError, match="not projectable"):
        codec_for("decoded").render_frame(spec, "proj_u")
    with pytest.raises(FormatError, match="no reconstruction for codec 'moire'"):
        codec_for("moire")


def test_full_coordinate_says_which_samples_carry_both_projector_coordinates():
    from ringscan.pipeline.codecs.registry import codec_for

    base = {"width": 1024, "height": 768, "center": [511.5, 383.5], "rho0": 8.0, "pitch": 16.0}
    decoded = parse_patterns({**base, "codec": "decoded", "rho0": 0.0, "pitch": 1.0})
    assert codec_for("decoded").full_coordinate(decoded)
    for name in ("gray-rings", "phase-rings"):
        extra = {"bits": 5, "sector_bits": 6}
        with_angle = parse_patterns({**base, **extra, "codec": name, "angle_steps": 4})
        without = parse_patterns({**base, **extra, "codec": name, "angle_steps": 0})
        assert codec_for(name).full_coordinate(with_angle) and not codec_for(name).full_coordinate(without), name
    rings = parse_patterns({**base, "codec": "rings", "count": 20})
    assert not codec_for("rings").full_coordinate(rings)
    assert set(CODEC_CLASSES) == {"rings", "gray-rings", "phase-rings", "decoded"}  # a new codec: add it above


def test_code_outside_the_codecs_names_them_through_the_codecs_package():
    """The default codec and every codec's ``NAME`` are registered; whether a codec can
    carry the angle code is asked of the codec (``Codec.has_angle_code``)."""
    from ringscan.pipeline.codecs import DEFAULT_CODEC, decoded, gray_rings, phase_rings, rings

    assert DEFAULT_CODEC in CODECS
    assert [m.NAME for m in (rings, gray_rings, phase_rings, decoded)] == list(CODEC_CLASSES)
    assert {n: c.has_angle_code for n, c in all_codecs().items()} == {"rings": False, "gray-rings": True,
                                                                   "phase-rings": True, "decoded": False}
