"""Two-camera rigs and scans (docs/formats.md): the rig's camera2, an uncalibrated
projector, a view's camera-2 frames."""

import json

import cv2
import numpy as np
import pytest

from ringscan.pipeline.formats.errors import FormatError
from ringscan.pipeline.formats.images import write_image
from ringscan.pipeline.formats.packing import pack_scan, unpack_scan
from ringscan.pipeline.formats.patterns import frame_names, parse_patterns
from ringscan.pipeline.formats.rig import (
    default_rig,
    has_calibrated_light,
    load_rig,
    look_at,
    parse_rig,
    rig_to_dict,
    save_rig,
)
from ringscan.pipeline.formats.scan import (
    Scan,
    View,
    as_camera2,
    check_view_frames,
    load_scan,
    read_view_frames,
    save_scan,
)
from ringscan.pipeline.geometry import light_model_for, projector_pixels

GRAY = {"codec": "gray-rings", "width": 1024, "height": 768, "center": [511.5, 383.5], "rho0": 8, "pitch": 4,
        "bits": 3, "sector_bits": 2, "angle_steps": 0}


def _stereo_dict(*, light="uncalibrated", size1=(64, 48), size2=(80, 60)):
    d = rig_to_dict(default_rig(turntable=False))
    d["camera"].update(width=size1[0], height=size1[1])
    R2, t2 = look_at([60.0, -240.0, 360.0], [0.0, 0.0, 25.0])
    d["camera2"] = {**d["camera"], "width": size2[0], "height": size2[1], "R": R2.tolist(), "t": t2.tolist()}
    if light == "uncalibrated":
        d["light"] = {"model": "uncalibrated", "width": 1024, "height": 768}
    return d


def test_stereo_rig_round_trip(tmp_path):
    rig = parse_rig(_stereo_dict())
    assert rig.camera2 is not None and (rig.camera2.width, rig.camera2.height) == (80, 60)
    assert not has_calibrated_light(rig)
    save_rig(tmp_path / "rig.json", rig)
    back = load_rig(tmp_path / "rig.json")
    assert np.allclose(back.camera2.R, rig.camera2.R) and np.allclose(back.camera2.t, rig.camera2.t)
    assert back.light.model == "uncalibrated" and (back.light.width, back.light.height) == (1024, 768)
    # a calibrated projector with two cameras: all three are usable
    rig3 = parse_rig(_stereo_dict(light="parallel"))
    assert has_calibrated_light(rig3) and rig3.camera2 is not None
    # one-camera rigs are written as before (no camera2 key)
    assert "camera2" not in rig_to_dict(default_rig())


def test_uncalibrated_projector_cannot_be_triangulated_with():
    rig = parse_rig(_stereo_dict())
    with pytest.raises(FormatError, match="not calibrated.*camera-camera"):
        light_model_for(rig)
    with pytest.raises(FormatError, match="not calibrated"):
        projector_pixels(rig, np.zeros((1, 3)))


@pytest.mark.parametrize("edit,match", [
    (lambda d: d.pop("camera2"), "'uncalibrated' needs a second camera"),
    (lambda d: d["camera2"].pop("K"), "camera2.K"),
    (lambda d: d["camera2"].update(R=[[1, 0, 0], [0, 1, 0], [0, 0, 2]]), "camera2.R"),
    (lambda d: d["camera2"].update(R=np.diag([1.0, -1, -1]).tolist(), t=[0, 0, -100]), "camera2: the working volume is behind"),
    (lambda d: d.update(camera2=dict(d["camera"])), "camera2: at the same place as camera"),
    (lambda d: d.update(camera2=[1, 2]), "camera2: missing or not an object"),
    (lambda d: d["light"].pop("width"), "light"),
])
def test_bad_stereo_rig(tmp_path, edit, match):
    d = _stereo_dict()
    edit(d)
    p = tmp_path / "rig.json"
    p.write_text(json.dumps(d))
    with pytest.raises(FormatError, match=match) as e:
        load_rig(p)
    assert str(p) in str(e.value)


def _write_stereo_scan(folder, *, size2=(80, 60), second=True):
    rig = parse_rig(_stereo_dict(size2=size2))
    spec = parse_patterns(GRAY)
    f1, f2 = {}, {}
    for i, n in enumerate(frame_names(spec)):
        write_image(folder / "view_000" / f"{n}.png", np.full((48, 64), i, np.uint8))
        write_image(folder / "view_000" / "cam2" / f"{n}.png", np.full((60, 80), 100 + i, np.uint8))
        f1[n], f2[n] = f"view_000/{n}.png", f"view_000/cam2/{n}.png"
    v2 = View("view_000", 0.0, f2) if second else None
    scan = Scan(folder=folder, rig=rig, patterns=spec, views=(View("view_000", 0.0, f1, camera2=v2),))
    save_scan(scan)
    return scan


def test_two_camera_scan_round_trip(tmp_path):
    _write_stereo_scan(tmp_path)
    d = json.loads((tmp_path / "scan.json").read_text())
    assert d["format"] == "ringscan.scan/1" and "frames" in d["views"][0]["camera2"]
    scan = load_scan(tmp_path)
    view = scan.views[0]
    check_view_frames(scan, view)
    one = read_view_frames(scan, view)
    assert one.shape[1:] == (48, 64) and one[3, 0, 0] == 3
    s2 = as_camera2(scan)
    assert (s2.rig.camera.width, s2.rig.camera2.width) == (80, 64)
    two = read_view_frames(s2, view.camera2)
    assert two.shape[1:] == (60, 80) and two[3, 0, 0] == 103


def test_two_camera_scan_errors(tmp_path):
    # camera 2's frames of the wrong size: named by file, before anything is read
    scan = _write_stereo_scan(tmp_path / "a")
    d = _stereo_dict(size2=(81, 60))
    (tmp_path / "a" / "scan.json").write_text(json.dumps({**json.loads((tmp_path / "a" / "scan.json").read_text()),
                                                          "rig": d}))
    scan = load_scan(tmp_path / "a")
    with pytest.raises(FormatError, match=r"cam2/white.png: frame is 80x60, but the camera is 81x60"):
        check_view_frames(scan, scan.views[0])
    # one camera's frame missing
    scan = _write_stereo_scan(tmp_path / "b")
    (tmp_path / "b" / "view_000" / "cam2" / "gray_1.png").unlink()
    with pytest.raises(FormatError, match=r"cam2/gray_1.png: frame 'gray_1' of view_000 \(camera 2\) not found"):
        load_scan(tmp_path / "b")
    # camera-2 frames with a one-camera rig
    _write_stereo_scan(tmp_path / "c")
    p = tmp_path / "c" / "scan.json"
    d = json.loads(p.read_text())
    d["rig"] = rig_to_dict(default_rig())
    p.write_text(json.dumps(d))
    with pytest.raises(FormatError, match=r"views\[0\].camera2: the rig has one camera"):
        load_scan(tmp_path / "c")
    # a view without camera 2 is a camera-projector view
    scan = _write_stereo_scan(tmp_path / "d", second=False)
    assert load_scan(tmp_path / "d").views[0].camera2 is None
    with pytest.raises(FormatError, match="one camera"):
        as_camera2(Scan(folder=tmp_path, rig=default_rig(), patterns=scan.patterns, views=()))


def test_pack_and_unpack_convert_camera_2_too(tmp_path):
    scan = _write_stereo_scan(tmp_path)
    before = {v.name: (read_view_frames(scan, v), read_view_frames(as_camera2(scan), v.camera2)) for v in scan.views}
    res = pack_scan(tmp_path)
    assert res.converted == ["view_000"] and res.removed == 2 * len(scan.views[0].frames)
    packed = load_scan(tmp_path)
    v = packed.views[0]
    assert v.packed == "view_000/frames.zarr" and v.camera2.packed == "view_000/cam2/frames.zarr"
    assert not list(tmp_path.rglob("*.png"))
    assert np.array_equal(read_view_frames(packed, v), before["view_000"][0])
    assert np.array_equal(read_view_frames(as_camera2(packed), v.camera2), before["view_000"][1])
    assert pack_scan(tmp_path).already == ["view_000"]
    res = unpack_scan(tmp_path)
    assert res.converted == ["view_000"] and res.removed == 2
    back = load_scan(tmp_path)
    v = back.views[0]
    assert v.packed is None and v.camera2.packed is None and not list(tmp_path.rglob("frames.zarr"))
    assert set(v.camera2.frames.values()) == {f"view_000/cam2/{n}.png" for n in v.camera2.frames}
    assert np.array_equal(read_view_frames(as_camera2(back), v.camera2), before["view_000"][1])


def test_pack_of_a_two_camera_scan_with_a_bad_camera_2_frame_writes_nothing(tmp_path):
    scan = _write_stereo_scan(tmp_path)
    # a colour frame of camera 2: refused before any store is written
    p = tmp_path / scan.views[0].camera2.frames["white"]
    cv2.imwrite(str(p), np.zeros((60, 80, 3), np.uint8))
    before = sorted(q.relative_to(tmp_path) for q in tmp_path.rglob("*"))
    with pytest.raises(FormatError, match=r"cam2/white.png: colour frame"):
        pack_scan(tmp_path)
    assert sorted(q.relative_to(tmp_path) for q in tmp_path.rglob("*")) == before


def test_pack_keep_then_pack_removes_both_cameras_leftovers(tmp_path):
    scan = _write_stereo_scan(tmp_path)
    n = len(scan.views[0].frames)
    assert pack_scan(tmp_path, keep=True).removed == 0
    assert len(list(tmp_path.rglob("*.png"))) == 2 * n  # a killed run leaves these too
    res = pack_scan(tmp_path)
    assert res.already == ["view_000"] and res.removed == 2 * n and not list(tmp_path.rglob("*.png"))


def test_unpack_with_camera_2s_store_damaged_writes_nothing(tmp_path):
    """Before: camera 1's PNGs were written beside its store, then camera 2's damaged chunk stopped the run."""
    _write_stereo_scan(tmp_path)
    pack_scan(tmp_path)
    chunk = tmp_path / "view_000" / "cam2" / "frames.zarr" / "c" / "3" / "0" / "0"
    raw = chunk.read_bytes()
    chunk.write_bytes(raw[:-5] + bytes([raw[-5] ^ 1]) + raw[-4:])  # intact size and header: its CRC32C fails
    before = sorted(q.relative_to(tmp_path) for q in tmp_path.rglob("*"))
    scan_json = (tmp_path / "scan.json").read_bytes()
    with pytest.raises(FormatError, match="CRC32C") as e:
        unpack_scan(tmp_path)
    assert e.value.path == str(chunk)
    assert sorted(q.relative_to(tmp_path) for q in tmp_path.rglob("*")) == before
    assert (tmp_path / "scan.json").read_bytes() == scan_json
