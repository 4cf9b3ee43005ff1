"""The JSON Schemas of the rig file and scan.json (``ringscan schema rig|scan``) against the loaders:
every file ringscan writes validates; broken files that the loaders refuse fail the schema too."""

from __future__ import annotations

import copy
import json

import numpy as np
import pytest

from ringscan.pipeline.formats.errors import FormatError
from ringscan.pipeline.formats.rig import default_rig, parse_rig, rig_to_dict
from ringscan.pipeline.formats.schemas import rig_json_schema, scan_json_schema
from ringscan.tools.cli import main

jsonschema = pytest.importorskip("jsonschema", reason="the schema tests need jsonschema: pip install '.[test]'")


def _validator(schema):
    cls = jsonschema.validators.validator_for(schema)
    cls.check_schema(schema)  # the schema itself is valid draft 2020-12
    return cls(schema)


RIG = _validator(rig_json_schema())
SCAN = _validator(scan_json_schema())


def _errors(validator, doc) -> list[str]:
    return [f"{'/'.join(map(str, e.absolute_path))}: {e.message}" for e in validator.iter_errors(doc)]


def _json(d):
    """As read back from a file (tuples -> lists, NumPy scalars -> numbers)."""
    return json.loads(json.dumps(d, default=lambda o: o.item() if hasattr(o, "item") else str(o)))


@pytest.mark.parametrize("kw", [{}, {"light_model": "perspective"}, {"turntable": False}, {"gamma": 1.0}])
def test_default_rigs_validate(kw):
    d = _json(rig_to_dict(default_rig(**kw)))
    assert _errors(RIG, d) == []


def _two_camera_rig(model="uncalibrated") -> dict:
    """The two-camera rig of docs/formats.md (STEREO_CONTRACT): camera2 beside camera, an uncalibrated projector."""
    d = _json(rig_to_dict(default_rig()))
    cam2 = copy.deepcopy(d["camera"])
    cam2["t"] = [d["camera"]["t"][0] - 60.0, *d["camera"]["t"][1:]]
    d["camera2"] = cam2
    if model == "uncalibrated":
        d["light"] = {"model": "uncalibrated", "width": 1024, "height": 768}
    return d


def test_two_camera_rigs_validate():
    assert _errors(RIG, _two_camera_rig()) == []
    assert _errors(RIG, _two_camera_rig("parallel")) == []
    bad = _two_camera_rig()
    del bad["camera2"]  # an uncalibrated projector needs a second camera
    assert _errors(RIG, bad)
    bad["camera2"] = None
    assert _errors(RIG, bad)
    bad = _two_camera_rig()
    bad["camera2"] = [1, 2]
    assert _errors(RIG, bad)
    bad["camera2"] = {**_two_camera_rig()["camera2"], "width": 0}
    assert _errors(RIG, bad)


# Broken rigs: each is refused by the loader and must fail the schema.
def _set(path, value):
    def edit(d):
        *keys, last = path
        for k in keys:
            d = d[k]
        if value is _DELETE:
            del d[last]
        else:
            d[last] = value
    return edit


_DELETE = object()
BROKEN_RIGS = {
    "format": _set(["format"], "ringscan.rig/9"),
    "units": _set(["units"], "inch"),
    "no camera": _set(["camera"], _DELETE),
    "camera width a string": _set(["camera", "width"], "1280"),
    "camera width 0": _set(["camera", "width"], 0),
    "camera width too big": _set(["camera", "width"], 70000),
    "camera width a bool": _set(["camera", "width"], True),
    "K 2x3": _set(["camera", "K"], [[2600, 0, 639.5], [0, 2600, 511.5]]),
    "K last row": _set(["camera", "K"], [[2600, 0, 639.5], [0, 2600, 511.5], [0, 1, 1]]),
    "K focal 0.5": _set(["camera", "K"], [[0.5, 0, 639.5], [0, 2600, 511.5], [0, 0, 1]]),
    "dist 3 values": _set(["camera", "dist"], [0.1, 0.2, 0.3]),
    "dist huge": _set(["camera", "dist"], [1e4, 0, 0, 0, 0]),
    "dist 6 values": _set(["camera", "dist"], [0.1, 0, 0, 0, 0, 0.2]),
    "dist 9 values": _set(["camera", "dist"], [0.1, 0, 0, 0, 0, 0.2, 0, 0, 0.001]),
    "dist tilted sensor": _set(["camera", "dist"], [0.1, 0, 0, 0, 0, 0.2, 0, 0, 0, 0, 0, 0, 0.01, 0]),
    "light dist 7 values": _set(["light"], {"model": "perspective", "width": 1024, "height": 768,
                                            "K": [[3800, 0, 511.5], [0, 3800, 383.5], [0, 0, 1]],
                                            "dist": [0.1, 0, 0, 0, 0, 0.2, 0],
                                            "R": [[1, 0, 0], [0, -1, 0], [0, 0, -1]], "t": [0, 0, 600]}),
    "t 2 values": _set(["camera", "t"], [1, 2]),
    "t too far": _set(["camera", "t"], [0, 0, 1e6]),
    "R a string": _set(["camera", "R"], "identity"),
    "gamma 50": _set(["camera", "response"], {"gamma": 50}),
    "response without gamma": _set(["camera", "response"], {}),
    "light model": _set(["light", "model"], "laser"),
    "no light": _set(["light"], _DELETE),
    "pitch 0": _set(["light", "pixel_pitch_mm"], 0),
    "axis_px 3": _set(["light", "axis_px"], [1, 2, 3]),
    "no axis_px": _set(["light", "axis_px"], _DELETE),
    "light R null": _set(["light", "R"], None),
    "volume r_max 0": _set(["volume", "r_max"], 0),
    "volume z_min a string": _set(["volume", "z_min"], "low"),
    "no volume": _set(["volume"], _DELETE),
    "turntable axis 2": _set(["turntable", "axis_dir"], [0, 1]),
    "turntable a list": _set(["turntable"], [0, 0, 1]),
    "uncalibrated one camera": _set(["light"], {"model": "uncalibrated", "width": 1024, "height": 768}),
}


@pytest.mark.parametrize("name", list(BROKEN_RIGS))
def test_a_broken_rig_fails_the_schema_and_the_loader(name):
    d = _json(rig_to_dict(default_rig()))
    BROKEN_RIGS[name](d)
    with pytest.raises(FormatError):
        parse_rig(d, source="rig.json")
    assert _errors(RIG, d), f"{name}: the schema takes a rig the loader refuses"


def test_what_the_loader_takes_the_schema_takes():
    """Optional and null fields the loader reads as absent."""
    d = _json(rig_to_dict(default_rig()))
    d["camera"]["dist"] = None
    d["camera"]["response"] = None
    d["turntable"] = None
    d["camera2"] = None
    d["camera"]["dist"] = [0.01, 0.0, 0.0, 0.0]  # four coefficients
    del d["light"]["width"], d["light"]["height"], d["light"]["R"], d["light"]["t"]
    d["units"] = "mm"
    d["comment"] = "kept"  # unknown keys are accepted
    parse_rig(d)
    assert _errors(RIG, d) == []
    # OpenCV's rational (8) and thin-prism (12) models; 14 with a zero tilt
    for dist in ([0.1, 0.01, 0, 0, 0, 0.2, 0, 0], [0.1, 0.01, 0, 0, 0, 0.2, 0, 0, 1e-3, 0, 0, 1e-4],
                 [0.1, 0.01, 0, 0, 0, 0.2, 0, 0, 1e-3, 0, 0, 1e-4, 0, 0]):
        d["camera"]["dist"] = dist
        parse_rig(d)
        assert _errors(RIG, d) == [], len(dist)


# ----------------------------------------------------------------------------- scan.json


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    from tests.support.tiny_scan import simulate_tiny_scan

    return simulate_tiny_scan(tmp_path_factory.mktemp("schema") / "scan", turntable_deg=(0.0, 90.0)).folder


def _scan_json(folder):
    return json.loads((folder / "scan.json").read_text())


def test_simulated_and_packed_scans_validate(tiny, tmp_path):
    import shutil

    from ringscan.pipeline.formats.packing import pack_scan

    d = _scan_json(tiny)
    assert "truth" in d and _errors(SCAN, d) == []
    packed = tmp_path / "packed"
    shutil.copytree(tiny, packed)
    assert pack_scan(packed).converted
    d = _scan_json(packed)
    assert d["format"] == "ringscan.scan/2" and "packed" in d["views"][0] and _errors(SCAN, d) == []
    d["format"] = "ringscan.scan/1"  # packed views need scan/2
    assert _errors(SCAN, d)


def test_a_scan_with_a_rig_file_validates(tiny):
    d = _scan_json(tiny)
    d["rig"] = "rig.json"
    assert _errors(SCAN, d) == []
    for bad in ("../rig.json", "/etc/rig.json", "a/../../rig.json", "", 7):
        d["rig"] = bad
        assert _errors(SCAN, d), bad


def test_a_scan_with_frame_bits_validates(tiny):
    d = _scan_json(tiny)
    for bits in (8, 10, 12, 16):
        d["frame_bits"] = bits
        assert _errors(SCAN, d) == [], bits


def test_the_cli_writes_these_schemas(tmp_path, capsys):
    assert main(["schema", "rig"]) == 0
    assert json.loads(capsys.readouterr().out) == rig_json_schema()
    assert main(["schema", "scan", "--out", str(tmp_path / "scan.schema.json")]) == 0
    assert json.loads((tmp_path / "scan.schema.json").read_text()) == scan_json_schema()


def test_imported_scans_validate(tmp_path, capsys):
    """`ringscan import` output (the decoded codec, the rig in a file beside scan.json)."""
    from ringscan.pipeline.formats.rig import save_rig
    from tests.support.opencv_graycode_rig import PH, PW, small_procam_rig

    save_rig(tmp_path / "rig.json", small_procam_rig())
    out, scan = tmp_path / "render", tmp_path / "scan"
    assert main(["simulate", "--rig", str(tmp_path / "rig.json"), "--scene", "sphere", "--size-mm", "50",
                 "--captures", "opencv-graycode", "--no-progress", "--device", "cpu", "--out", str(out)]) == 0
    assert main(["import", str(out / "capture_0"), "--rig", str(out / "rig.json"), "--projector", f"{PW}x{PH}",
                 "--out", str(scan)]) == 0
    capsys.readouterr()
    d = _scan_json(scan)
    assert d["patterns"]["codec"] == "decoded" and _errors(SCAN, d) == []
    d["patterns"]["precompensated_gamma"] = 2.2  # nothing is projected: refused
    assert _errors(SCAN, d)
    del d["patterns"]["precompensated_gamma"]
    rig = d["rig"] if isinstance(d["rig"], dict) else json.loads((scan / d["rig"]).read_text())
    assert _errors(RIG, rig) == []
    assert _errors(RIG, json.loads((out / "rig.json").read_text())) == []


def _two_camera_scan(tiny, *, packed=False):
    d = _scan_json(tiny)
    d["rig"] = _two_camera_rig("parallel")
    d["rig"]["camera"] = d["rig"]["camera2"] = _scan_json(tiny)["rig"]["camera"]
    d["rig"]["camera2"] = {**d["rig"]["camera2"], "t": [v + 50.0 for v in d["rig"]["camera2"]["t"]]}
    v = d["views"][0]
    if packed:
        d["format"] = "ringscan.scan/2"
        v["camera2"] = {"packed": {"store": "view_000/cam2.zarr", "frames": list(v["frames"])}}
    else:
        v["camera2"] = {"frames": {k: f"view_000/cam2/{k}.png" for k in v["frames"]}}
    return d


def test_two_camera_scans_validate(tiny):
    assert _errors(SCAN, _two_camera_scan(tiny)) == []
    assert _errors(SCAN, _two_camera_scan(tiny, packed=True)) == []
    d = _two_camera_scan(tiny, packed=True)
    d["format"] = "ringscan.scan/1"  # camera 2's packed frames need scan/2 as well
    assert _errors(SCAN, d)
    d = _two_camera_scan(tiny)
    d["views"][0]["camera2"] = {"frames": {"white": "../white.png"}}
    assert _errors(SCAN, d)
    d["views"][0]["camera2"] = {}  # neither frames nor packed
    assert _errors(SCAN, d)


BROKEN_SCANS = {
    "format": _set(["format"], "ringscan.scan/7"),
    "no views": _set(["views"], _DELETE),
    "views an object": _set(["views"], {}),
    "view a list": _set(["views", 0], []),
    "view name with a slash": _set(["views", 0, "name"], "a/b"),
    "view name hidden": _set(["views", 0, "name"], ".hidden"),
    "view name with a newline": _set(["views", 0, "name"], "new\nline"),
    "turntable_deg a string": _set(["views", 0, "turntable_deg"], "90"),
    "frames null": _set(["views", 0, "frames"], None),
    "no frames": _set(["views", 0, "frames"], _DELETE),
    "frame leaves the folder": _set(["views", 0, "frames", "white"], "../white.png"),
    "frame absolute": _set(["views", 0, "frames", "white"], "/tmp/white.png"),
    "frames and packed": _set(["views", 0, "packed"], {"store": "s.zarr", "frames": ["white"]}),
    "patterns codec": _set(["patterns", "codec"], "stripes"),
    "patterns width 0": _set(["patterns", "width"], 0),
    "patterns bits 40": _set(["patterns", "bits"], 40),
    "patterns no bits": _set(["patterns", "bits"], _DELETE),
    "patterns pitch 0": _set(["patterns", "pitch"], 0),
    "patterns center 1": _set(["patterns", "center"], [1]),
    "patterns rho0 -1": _set(["patterns", "rho0"], -1),
    "rig 5": _set(["rig"], 5),
    "rig camera width": _set(["rig", "camera", "width"], -1),
    "truth mesh outside": _set(["truth", "mesh"], "../outside.ply"),
    "truth mesh 5": _set(["truth", "mesh"], 5),
    "truth views null": _set(["truth", "views"], None),
    "truth view depth 7": _set(["truth", "views", "view_000", "depth"], 7),
    "frame_bits 0": _set(["frame_bits"], 0),
    "frame_bits 7": _set(["frame_bits"], 7),
    "frame_bits 17": _set(["frame_bits"], 17),
    "frame_bits a string": _set(["frame_bits"], "12"),
    "frame_bits true": _set(["frame_bits"], True),
}


@pytest.mark.parametrize("name", list(BROKEN_SCANS))
def test_a_broken_scan_fails_the_schema_and_the_loader(name, tiny, tmp_path):
    import shutil

    from ringscan.pipeline.formats.scan import check_truth, load_scan

    d = _scan_json(tiny)
    BROKEN_SCANS[name](d)
    folder = tmp_path / "scan"
    shutil.copytree(tiny, folder)
    (folder / "scan.json").write_text(json.dumps(d))
    with pytest.raises(FormatError):
        check_truth(load_scan(folder)) if name.startswith("truth") else load_scan(folder)
    assert _errors(SCAN, d), f"{name}: the schema takes a scan.json the loader refuses"


def test_the_schemas_describe_their_fields():
    r = rig_json_schema()
    cam = r["$defs"]["Camera"]["properties"]
    assert cam["K"]["description"].startswith("3x3 intrinsic matrix")
    assert "R R^T = I" in cam["R"]["description"]
    assert set(r["properties"]["light"]["discriminator"]["mapping"]) == {"parallel", "perspective", "uncalibrated"}
    s = scan_json_schema()
    codecs = set(s["properties"]["patterns"]["discriminator"]["mapping"])
    from ringscan.pipeline.formats.patterns import PATTERN_LAYOUTS

    assert codecs == set(PATTERN_LAYOUTS)
    assert np.isclose(s["$defs"]["Patterns_gray_rings"]["properties"]["bits"]["maximum"], 16)
