"""scan.json, rig files and pattern parameters: valid input loads, every kind of
bad input is a FormatError that names the file and the field."""

import json
import math

import numpy as np
import pytest

from ringscan.pipeline.codecs.render import render_frame
from ringscan.pipeline.formats.errors import FormatError
from ringscan.pipeline.formats.images import write_image
from ringscan.pipeline.formats.meshes import read_cloud
from ringscan.pipeline.formats.patterns import frame_names, gray_decode, gray_encode, parse_patterns
from ringscan.pipeline.formats.ply import check_ply, read_ply, write_ply
from ringscan.pipeline.formats.rig import default_rig, load_rig, parse_rig, rig_to_dict, save_rig, turntable_transform
from ringscan.pipeline.formats.scan import Scan, View, check_truth, load_scan, read_view_frames, save_scan

GRAY = {"codec": "gray-rings", "width": 64, "height": 48, "center": [31.5, 23.5], "rho0": 2.0, "pitch": 2.0,
        "bits": 4, "sector_bits": 2}


def _rig_dict():
    return rig_to_dict(default_rig())


def test_rig_round_trip(tmp_path):
    rig = default_rig()
    save_rig(tmp_path / "rig.json", rig)
    back = load_rig(tmp_path / "rig.json")
    assert np.allclose(back.camera.K, rig.camera.K) and np.allclose(back.camera.R, rig.camera.R)
    assert back.camera.gamma == 2.2 and back.light.pixel_pitch_mm == 0.15
    # The default camera: 420 mm from (0, 0, 25), 35 degrees off the light axis on the -y side.
    c = back.camera.center - np.array([0, 0, 25.0])
    assert math.isclose(np.linalg.norm(c), 420.0, rel_tol=1e-9)
    assert math.isclose(math.degrees(math.acos(c[2] / 420.0)), 35.0, rel_tol=1e-9) and c[1] < 0 and abs(c[0]) < 1e-9


@pytest.mark.parametrize("dist,kept", [
    ([0.02, -0.05, 0.001, 0.0], [0.02, -0.05, 0.001, 0.0, 0.0]),  # OpenCV's 4: k3 = 0, written as 5 (as always)
    ([0.02, -0.05, 0.001, 0.0, 0.01], None),
    ([1.8, 0.6, 0.001, -0.0005, 0.02, 2.1, 1.2, 0.15], None),  # CALIB_RATIONAL_MODEL
    ([1.8, 0.6, 0.001, -0.0005, 0.02, 2.1, 1.2, 0.15, 0.002, -0.0005, -0.001, 0.0003], None),  # + THIN_PRISM
    ([1.8, 0.6, 0.001, -0.0005, 0.02, 2.1, 1.2, 0.15, 0.002, -0.0005, -0.001, 0.0003, 0.0, 0.0],  # + zero tilt
     [1.8, 0.6, 0.001, -0.0005, 0.02, 2.1, 1.2, 0.15, 0.002, -0.0005, -0.001, 0.0003]),
])
def test_rig_lens_models_round_trip(tmp_path, dist, kept):
    """Camera, second camera and projector take OpenCV's 4-, 5-, 8-, 12- and (zero-tilt)
    14-coefficient lenses and write them back as given (4 as 5, 14 as 12)."""
    d = rig_to_dict(default_rig(light_model="perspective"))
    d["camera"]["dist"] = dist
    d["camera2"] = {**d["camera"], "t": (np.array(d["camera"]["t"]) + [60.0, 0, 0]).tolist()}
    d["light"]["dist"] = dist
    p = tmp_path / "rig.json"
    p.write_text(json.dumps(d))
    rig = load_rig(p)
    save_rig(tmp_path / "back.json", rig)
    back = json.loads((tmp_path / "back.json").read_text())
    for dev in (back["camera"], back["camera2"], back["light"]):
        assert dev["dist"] == (kept or dist)
    assert rig_to_dict(load_rig(tmp_path / "back.json")) == back


def test_a_five_coefficient_rig_writes_back_as_before():
    rig = default_rig()
    d = rig_to_dict(rig)
    assert d["camera"]["dist"] == [0.02, -0.05, 0.0, 0.0, 0.0]
    assert rig_to_dict(parse_rig(json.loads(json.dumps(d)))) == d


@pytest.mark.parametrize("edit,match", [
    (lambda d: d.update(format="ringscan.rig/9"), "unknown rig format"),
    (lambda d: d["camera"].update(K=[[0, 0, 1], [0, 1, 1], [0, 0, 1]]), "camera.K: singular"),
    (lambda d: d["camera"].update(R=[[1, 0, 0], [0, 1, 0], [0, 0, 2]]), "camera.R: not a rotation"),
    (lambda d: d["camera"].update(t=[0, float("nan"), 1]), "camera.t: contains non-finite"),
    (lambda d: d["light"].update(model="laser"), "light.model"),
    (lambda d: d["light"].update(pixel_pitch_mm=-1), "pixel_pitch_mm: must be > 0"),
    (lambda d: d["volume"].update(z_max=-10), "z_max must be greater"),
    (lambda d: d["camera"].update(width=0), "camera.width"),
    (lambda d: d.pop("camera"), "camera: missing"),
    # absurd but finite numbers, and numbers given as strings (docs/formats.md, "sane ranges")
    (lambda d: d["camera"].update(t=[0, 0, 1e300]), "camera.t: 1e\\+300 is outside the sane range"),
    (lambda d: d["light"].update(pixel_pitch_mm=1e-300), "light.pixel_pitch_mm: 1e-300 is outside the sane range"),
    (lambda d: d["camera"].update(K=[[1e300, 0, 639.5], [0, 1e300, 511.5], [0, 0, 1]]),
     "camera.K: focal lengths 1e\\+300, 1e\\+300 px are outside the sane range"),
    (lambda d: d["camera"].update(K=[["2600", 0, 639.5], [0, 2600, 511.5], [0, 0, 1]]),
     "camera.K: expected numbers of shape \\(3, 3\\), got '2600'"),
    (lambda d: d["camera"].update(width="1280"), "camera.width: expected a positive integer, got '1280'"),
    (lambda d: d["camera"].update(dist=["0.02", 0, 0, 0, 0]), "camera.dist: expected 4, 5, 8 or 12 finite"),
    # OpenCV writes 4, 5, 8, 12 or 14 coefficients: any other count is a broken file
    (lambda d: d["camera"].update(dist=[0.02, 0, 0, 0, 0, 0.1]), "camera.dist: expected 4, 5, 8 or 12 finite"),
    (lambda d: d["camera"].update(dist=[0.02, 0, 0, 0, 0, 0.1, 0]), "camera.dist: expected 4, 5, 8 or 12 finite"),
    (lambda d: d["camera"].update(dist=[0.02, 0, 0, 0, 0, 0.1, 0, 0, 1e-3]),
     "camera.dist: expected 4, 5, 8 or 12 finite"),
    (lambda d: d["camera"].update(dist=[0.02, 0, 0, 0, 0, float("nan"), 0, 0]),
     "camera.dist: expected 4, 5, 8 or 12 finite"),
    (lambda d: d["camera"].update(dist=[0.02, 0, 0, 0, 0, 0.1, 0, 0, 0, 0, 0, 0, 0.001, 0]),
     "camera.dist: tilted-sensor model \\(taux, tauy\\) not supported"),
    (lambda d: d.update(camera2={**d["camera"], "t": [50.0, 0.0, 400.0],
                                 "dist": [0.02, 0, 0, 0, 0, 0.1, 0, 0, 0, 0, 0, 0, 0, -0.002]}),
     "camera2.dist: tilted-sensor model"),
    (lambda d: d["camera"].update(dist=[0.02, 0, 0, 0, 0, 0.1, 0, 0, 0, 0, 0, 2e3]),
     "camera.dist: 2000 is outside the sane range"),
    (lambda d: d["camera"].update(dist=[1e6, 0, 0, 0, 0]), "camera.dist: 1e\\+06 is outside the sane range"),
    (lambda d: d["camera"].update(response={"gamma": 1e300}), "camera.response.gamma: 1e\\+300 is outside"),
    (lambda d: d["light"].update(pixel_pitch_mm="0.15"), "light.pixel_pitch_mm: expected a number, got '0.15'"),
    (lambda d: d["light"].update(width="650"), "light.width: expected a positive integer, got '650'"),
    (lambda d: d["light"].update(axis_px=[511.5, 1e300]), "light.axis_px: 1e\\+300 is outside the sane range"),
    (lambda d: d["volume"].update(r_max=1e300), "volume.r_max: 1e\\+300 is outside the sane range"),
    (lambda d: d["volume"].update(z_min="0"), "volume.z_min: expected a number, got '0'"),
    (lambda d: d["camera"].update(width=10**9), "camera.width: 1000000000 px is outside the sane range"),
    (lambda d: d["camera"].update(R=[[1, 0, 0], [0, 1, 0], [0, 0, 1]], t=[0, 0, -1000]),
     "the working volume is behind the camera"),
])
def test_bad_rig(tmp_path, edit, match):
    d = _rig_dict()
    edit(d)
    p = tmp_path / "rig.json"
    p.write_text(json.dumps(d, allow_nan=True))
    with pytest.raises(FormatError, match=match) as e:
        load_rig(p)
    assert str(p) in str(e.value)


def test_rig_not_json(tmp_path):
    p = tmp_path / "rig.json"
    p.write_text("{not json")
    with pytest.raises(FormatError, match="not valid JSON"):
        load_rig(p)
    with pytest.raises(FormatError, match="file not found"):
        load_rig(tmp_path / "missing.json")


def test_turntable_transform_turns_right_handed():
    rig = default_rig()
    T = turntable_transform(rig.turntable, 90.0)
    assert np.allclose(T[:3, :3] @ [1, 0, 0], [0, 1, 0])  # +x -> +y about +z
    assert np.allclose(turntable_transform(rig.turntable, 0.0), np.eye(4))


def test_patterns_and_gray_code():
    k = np.arange(1024)
    assert np.array_equal(gray_decode(gray_encode(k), 10), k)
    assert np.all(np.bitwise_count(gray_encode(k[1:]) ^ gray_encode(k[:-1])) == 1)
    spec = parse_patterns(GRAY)
    names = frame_names(spec)
    assert names[:2] == ["white", "black"] and len(names) == 2 + 2 * 4 + 2 * 2
    f, inv = render_frame(spec, "gray_3"), render_frame(spec, "gray_3_inv")
    # frame + inverse = the coded annulus (one where lit, zero outside)
    s = f.astype(int) + inv
    v, u = np.mgrid[0:48, 0:64]
    rho = np.hypot(u - 31.5, v - 23.5)
    assert np.all(s[(rho > 3) & (rho < 33)] == 255) and np.all(s[rho < 1.4] == 0)
    p = parse_patterns(dict(codec="phase-rings", **{k: v for k, v in GRAY.items() if k != "codec"}))
    assert frame_names(p)[-4:] == ["phase_0", "phase_1", "phase_2", "phase_3"]


@pytest.mark.parametrize("edit,match", [
    ({"codec": "stripes"}, "unknown codec"),
    ({"center": [100, 5]}, "outside the 64x48 projector"),
    ({"pitch": 0}, "pitch: must be > 0"),
    ({"pitch": 0.5}, "below one projector pixel"),
    ({"bits": 40}, "bits: must be in"),
    ({"rho0": 500}, "outside the projector"),
    ({"rho0": -1}, "rho0: must be >= 0"),
])
def test_bad_patterns(edit, match):
    d = dict(GRAY)
    d.update(edit)
    with pytest.raises(FormatError, match=match):
        parse_patterns(d, source="scan.json")


def test_rings_that_do_not_fit():
    with pytest.raises(FormatError, match="only .* rings fit"):
        parse_patterns({"codec": "rings", "width": 64, "height": 48, "center": [31.5, 23.5], "rho0": 4,
                        "pitch": 6, "count": 30, "line_width": 2})


def _write_scan(tmp_path, *, size=(64, 48), dtype=np.uint8):
    rig = default_rig()
    d = rig_to_dict(rig)
    d["camera"].update(width=size[0], height=size[1])
    from ringscan.pipeline.formats.rig import parse_rig as pr

    rig = pr(d)
    spec = parse_patterns({**GRAY, "width": 1024, "height": 768, "center": [511.5, 383.5], "rho0": 8, "pitch": 4})
    frames = {}
    for n in frame_names(spec):
        write_image(tmp_path / "view_000" / f"{n}.png", np.full(size[::-1], 7, dtype))
        frames[n] = f"view_000/{n}.png"
    scan = Scan(folder=tmp_path, rig=rig, patterns=spec, views=(View("view_000", 0.0, frames),))
    save_scan(scan)
    return scan


def test_scan_round_trip(tmp_path):
    _write_scan(tmp_path)
    scan = load_scan(tmp_path)
    st = read_view_frames(scan, scan.views[0])
    assert st.shape == (2 + 8 + 4, 48, 64) and st.dtype == np.uint8 and np.all(st == 7)


def _edit_scan(tmp_path, fn):
    p = tmp_path / "scan.json"
    d = json.loads(p.read_text())
    fn(d)
    p.write_text(json.dumps(d))


@pytest.mark.parametrize("fn,match", [
    (lambda d: d.update(format="ringscan.scan/9"), "unknown scan format"),
    (lambda d: d["views"][0]["frames"].update(white="../../etc/passwd"), "leaves the scan folder"),
    (lambda d: d["views"][0]["frames"].update(white="/abs/white.png"), "leaves the scan folder"),
    (lambda d: d["views"][0]["frames"].pop("gray_2"), "missing frame\\(s\\) gray_2"),
    (lambda d: d["views"][0]["frames"].update(black="view_000/nothere.png"), "not found"),
    (lambda d: d["views"][0].update(turntable_deg="ten"), "turntable_deg"),
    (lambda d: d.update(rig="missing_rig.json"), "file not found"),
    (lambda d: d["patterns"].update(width=800), "does not match the rig's 1024x768"),
    # view names are file names: <name>.ply is written
    (lambda d: d["views"][0].update(name=".."), r"views\[0\].name: '..' is not a folder-safe name \(starts with a dot"),
    (lambda d: d["views"][0].update(name="."), "starts with a dot"),
    (lambda d: d["views"][0].update(name=".hidden"), "starts with a dot"),
    (lambda d: d["views"][0].update(name="a/b"), r"contains '/'"),
    (lambda d: d["views"][0].update(name="a:b"), r"contains ':'"),
    (lambda d: d["views"][0].update(name="v\x00"), r"contains '\\x00'"),
    (lambda d: d["views"][0].update(name=""), "expected a non-empty name"),
    (lambda d: d["views"].append({**d["views"][0], "name": "VIEW_000"}), "'VIEW_000' is not unique"),
    # a NUL (or another control character) in a path names scan.json and the field
    (lambda d: d["views"][0]["frames"].update(white="view_000/wh\x00ite.png"),
     r"views\[0\].frames.white: path 'view_000/wh\\x00ite.png' contains a control character"),
    (lambda d: d.update(rig="ri\x00g.json"), r"rig: path 'ri\\x00g.json' contains a control character"),
])
def test_bad_scan(tmp_path, fn, match):
    _write_scan(tmp_path)
    _edit_scan(tmp_path, fn)
    with pytest.raises(FormatError, match=match) as e:
        load_scan(tmp_path)
    assert "scan.json" in str(e.value) or "missing_rig.json" in str(e.value) or "nothere.png" in str(e.value)


def test_frame_paths_through_links(tmp_path):
    """A link inside the scan folder that stays inside is followed; one that leads out
    of the folder (a view folder linked to elsewhere) is refused, naming scan.json."""
    scan_dir = tmp_path / "scan"
    _write_scan(scan_dir)
    (scan_dir / "alias").symlink_to(scan_dir / "view_000", target_is_directory=True)
    _edit_scan(scan_dir, lambda d: d["views"][0]["frames"].update(white="alias/white.png"))
    assert load_scan(scan_dir).views[0].frames["white"] == "alias/white.png"
    outside = tmp_path / "elsewhere"
    (scan_dir / "view_000").rename(outside)
    (scan_dir / "view_000").symlink_to(outside, target_is_directory=True)
    with pytest.raises(FormatError, match=r"scan.json: views\[0\].frames.\w+: path '\w+/\w+.png' leaves the "
                                          r"scan folder \(through a link\)"):
        load_scan(scan_dir)


def test_a_frame_folder_that_is_a_link_to_itself_is_one_line(tmp_path):
    """A view folder (or a packed store) that is a symbolic link to itself: before, `RuntimeError: Symlink loop`
    out of pathlib in every command that loads the scan."""
    import shutil

    scan_dir = tmp_path / "scan"
    _write_scan(scan_dir)
    shutil.rmtree(scan_dir / "view_000")
    (scan_dir / "view_000").symlink_to("view_000")
    with pytest.raises(FormatError) as e:
        load_scan(scan_dir)
    assert e.value.path == str(scan_dir / "scan.json")
    assert str(e.value).endswith(f"cannot be followed: {scan_dir / 'view_000'} is a loop of symbolic links"), e.value


def test_scan_folder_errors(tmp_path):
    with pytest.raises(FormatError, match="nowhere: scan folder not found"):
        load_scan(tmp_path / "nowhere")
    with pytest.raises(FormatError, match="scan.json: file not found"):
        load_scan(tmp_path)
    (tmp_path / "scan.json").write_text("[1, 2]")
    with pytest.raises(FormatError, match="scan.json: expected a JSON object at the top level"):
        load_scan(tmp_path)
    _write_scan(tmp_path)
    _edit_scan(tmp_path, lambda d: d.update(views={"a": 1}))
    with pytest.raises(FormatError, match="scan.json: views: expected a list"):
        load_scan(tmp_path)


def test_binary_scan_json_names_the_file(tmp_path):
    _write_scan(tmp_path)
    (tmp_path / "scan.json").write_bytes(bytes(range(256)))
    with pytest.raises(FormatError, match=r"scan.json: not a text file: byte 0x80 at offset 128 is not UTF-8"):
        load_scan(tmp_path)


def test_save_scan_refuses_an_unsafe_view_name(tmp_path):
    scan = _write_scan(tmp_path)
    import dataclasses

    bad = dataclasses.replace(scan, views=(View("..", 0.0, dict(scan.views[0].frames)),))
    with pytest.raises(FormatError, match="not a folder-safe name"):
        save_scan(bad)


def test_bad_frames(tmp_path):
    scan = _write_scan(tmp_path)
    # a frame of another size
    write_image(tmp_path / "view_000" / "gray_1.png", np.zeros((10, 10), np.uint8))
    with pytest.raises(FormatError, match="gray_1.png: frame is 10x10, but the camera is 64x48"):
        read_view_frames(load_scan(tmp_path), scan.views[0])
    # a corrupt file
    (tmp_path / "view_000" / "gray_1.png").write_bytes(b"\x89PNG garbage")
    with pytest.raises(FormatError, match="gray_1.png: not a readable image"):
        read_view_frames(load_scan(tmp_path), scan.views[0])
    # a 16-bit frame among 8-bit ones
    write_image(tmp_path / "view_000" / "gray_1.png", np.zeros((48, 64), np.uint16))
    with pytest.raises(FormatError, match="uint16, other frames"):
        read_view_frames(load_scan(tmp_path), scan.views[0])


def test_colour_and_16bit_frames_read_as_grey(tmp_path):
    write_image(tmp_path / "c.png", np.dstack([np.full((4, 5), 10, np.uint8)] * 3))
    from ringscan.pipeline.formats.images import read_image

    g = read_image(tmp_path / "c.png")
    assert g.shape == (4, 5) and g.dtype == np.uint8 and np.all(g == 10)
    write_image(tmp_path / "d.tiff", np.full((4, 5), 4000, np.uint16))
    assert read_image(tmp_path / "d.tiff").dtype == np.uint16


def test_ply_of_many_blocks_round_trips_every_field(tmp_path):
    """write_ply fills its records a block of rows at a time: every value of every field (float32, int32, a
    float64 one, a strided column) comes back where it was, across several blocks and a part-block at the end."""
    from ringscan.pipeline.formats import ply

    rng = np.random.default_rng(1)
    n = 2 * ply._FILL_ROWS + 123
    pts = rng.normal(size=(n, 3)).astype(np.float32)
    fields = {"x": pts[:, 0], "y": pts[:, 1], "z": pts[:, 2], "ring": rng.integers(-1, 500, n).astype(np.int32),
              "w": rng.normal(size=n), "view": np.full(n, 7, np.int16)}
    write_ply(tmp_path / "m.ply", fields)
    back = read_ply(tmp_path / "m.ply")
    assert list(back) == list(fields)
    for k, a in fields.items():
        assert back[k].dtype == a.dtype and np.array_equal(back[k], a), k


def test_ply_round_trip_and_truncation(tmp_path):
    xyz = np.random.default_rng(0).normal(size=(100, 3)).astype(np.float32)
    write_ply(tmp_path / "a.ply", {"x": xyz[:, 0], "y": xyz[:, 1], "z": xyz[:, 2], "ring": np.arange(100, dtype=np.int32)})
    d = read_ply(tmp_path / "a.ply")
    assert np.array_equal(d["x"], xyz[:, 0]) and np.array_equal(d["ring"], np.arange(100))
    import open3d as o3d

    assert len(o3d.io.read_point_cloud(str(tmp_path / "a.ply")).points) == 100
    raw = (tmp_path / "a.ply").read_bytes()
    (tmp_path / "b.ply").write_bytes(raw[:-50])
    with pytest.raises(FormatError, match="truncated"):
        read_ply(tmp_path / "b.ply")
    assert not list(tmp_path.glob(".*tmp*"))  # no temporary files left behind
    # check_ply: whole files only, without reading the data
    assert check_ply(tmp_path / "a.ply") == 100
    for cut, match in ((len(raw) - 1, "truncated"), (40, "not a PLY file"), (0, "empty file")):
        (tmp_path / "c.ply").write_bytes(raw[:cut])
        with pytest.raises(FormatError, match=match):
            check_ply(tmp_path / "c.ply")
        with pytest.raises(FormatError, match=match):
            read_cloud(tmp_path / "c.ply")  # Open3D alone reads a truncated PLY up to where it ends


def test_png_frames_use_the_up_filter_and_round_trip(tmp_path):
    """Frames are written with the "up" row filter (docs/batch.md: ~30 % faster to
    decode than OpenCV's default "sub", same size); every row of the zlib stream
    starts with filter type 2, and the pixels come back exactly."""
    import struct
    import zlib

    import cv2

    rng = np.random.default_rng(1)
    img = np.clip(rng.normal(120, 20, (48, 64)), 0, 255).astype(np.uint8)
    write_image(tmp_path / "f.png", img)
    from ringscan.pipeline.formats.images import read_image

    assert np.array_equal(read_image(tmp_path / "f.png"), img)
    data = (tmp_path / "f.png").read_bytes()
    i, idat = 8, b""
    while i < len(data):
        (n,) = struct.unpack(">I", data[i:i + 4])
        if data[i + 4:i + 8] == b"IDAT":
            idat += data[i + 8:i + 8 + n]
        i += 12 + n
    rows = np.frombuffer(zlib.decompress(idat), np.uint8).reshape(48, 65)
    if not hasattr(cv2, "IMWRITE_PNG_FILTER"):
        pytest.skip("this OpenCV (< 4.11) cannot choose the PNG row filter")
    assert np.all(rows[:, 0] == 2)


def test_tiff_frames_are_written_uncompressed(tmp_path):
    """TIFF is the fast-to-read choice (docs/formats.md): no compression, so the file
    holds every pixel's bytes as they are, and it reads back exactly."""
    rng = np.random.default_rng(2)
    img = rng.integers(0, 4096, (48, 64)).astype(np.uint16)
    write_image(tmp_path / "f.tiff", img)
    from ringscan.pipeline.formats.images import read_image

    assert np.array_equal(read_image(tmp_path / "f.tiff"), img)
    data = (tmp_path / "f.tiff").read_bytes()
    assert len(data) >= img.nbytes
    assert img.tobytes() in data  # the strip is stored as is


GOOD_TRUTH = {"mesh": "truth/object.ply", "views": {"view_000": {"depth": "truth/d.tiff", "lit": "truth/l.png"}},
              "reference_plane_z": 0.0}


@pytest.mark.parametrize("edit,match", [
    (lambda t: t.update(mesh=5), r"truth.mesh: expected a relative path, got 5"),
    (lambda t: t.update(mesh=None), r"truth.mesh: expected a relative path, got None"),
    (lambda t: t.update(mesh=["a.ply"]), r"truth.mesh: expected a relative path, got \['a.ply'\]"),
    (lambda t: t.update(mesh="../outside.ply"), r"truth.mesh: path '../outside.ply' leaves the scan folder"),
    (lambda t: t.update(mesh="/etc/outside.ply"), r"truth.mesh: path '/etc/outside.ply' leaves the scan folder"),
    (lambda t: t.update(views=None), r"truth.views: expected an object"),
    (lambda t: t.update(views=[1]), r"truth.views: expected an object"),
    (lambda t: t["views"].update(view_000=7), r"truth.views.view_000: expected an object"),
    (lambda t: t["views"]["view_000"].update(depth=7), r"truth.views.view_000.depth: expected a relative path, got 7"),
    (lambda t: t["views"]["view_000"].update(lit="../x.png"), r"truth.views.view_000.lit: path '../x.png' leaves"),
    (lambda t: t.update(reference_plane_z="0"), r"truth.reference_plane_z: expected a finite number, got '0'"),
    (lambda t: t.update(reference_plane="no"), r"truth.reference_plane: expected true or false"),
])
def test_bad_truth_block(tmp_path, edit, match):
    scan = _write_scan(tmp_path)
    t = json.loads(json.dumps(GOOD_TRUTH))
    edit(t)
    scan = Scan(folder=scan.folder, rig=scan.rig, patterns=scan.patterns, views=scan.views, extra={"truth": t})
    with pytest.raises(FormatError, match=r"scan.json: " + match):
        check_truth(scan)


def test_truth_mesh_through_a_link_out_of_the_folder(tmp_path):
    scan = _write_scan(tmp_path / "scan")
    (tmp_path / "outside.ply").write_text("ply\n")
    (tmp_path / "scan" / "truth").symlink_to(tmp_path)
    scan = Scan(folder=scan.folder, rig=scan.rig, patterns=scan.patterns, views=scan.views,
                extra={"truth": {**GOOD_TRUTH, "mesh": "truth/outside.ply"}})
    with pytest.raises(FormatError, match=r"truth.mesh: path 'truth/outside.ply' leaves the scan folder \(through a"):
        check_truth(scan)
    scan = Scan(folder=scan.folder, rig=scan.rig, patterns=scan.patterns, views=scan.views, extra={"truth": GOOD_TRUTH})
    (tmp_path / "scan" / "truth").unlink()
    t = check_truth(scan)
    assert t["mesh"] == "truth/object.ply" and t["views"] == GOOD_TRUTH["views"] and t["reference_plane"] is True


def test_a_smooth_map_is_written_smaller_than_a_frame_and_read_back_exactly(tmp_path):
    """A decoded map (smooth 16-bit projector coordinates, as `ringscan import` writes them) is written with zlib's
    default strategy (``smooth=True``): read back to the bit, and far smaller than the run-length strategy that
    suits noisy camera frames makes it (where zlib finds long matches, run-length coding cannot use them)."""
    from ringscan.pipeline.formats.images import read_image

    y, x = np.mgrid[0:384, 0:512].astype(np.float64)
    u = np.round((40 + 0.37 * x + 0.02 * y + 3e-4 * x * y) * 64).astype(np.uint16)  # 1/64 px steps
    write_image(tmp_path / "map.png", u, smooth=True)
    write_image(tmp_path / "frame.png", u)
    assert np.array_equal(read_image(tmp_path / "map.png"), u) and np.array_equal(read_image(tmp_path / "frame.png"), u)
    assert (tmp_path / "map.png").stat().st_size < 0.8 * (tmp_path / "frame.png").stat().st_size
