"""scan.json's ``frame_bits`` (docs/formats.md): 16-bit frames of a 10- or 12-bit camera,
values LSB-aligned, read scaled to the full 16-bit range by bit replication; checked
against the frames as they are read."""

import json

import numpy as np
import pytest

from ringscan.pipeline.formats.errors import FormatError
from ringscan.pipeline.formats.frame_store import open_store
from ringscan.pipeline.formats.images import expand_frame_bits, read_image, write_image
from ringscan.pipeline.formats.packing import pack_scan, unpack_scan
from ringscan.pipeline.formats.patterns import frame_names, parse_patterns
from ringscan.pipeline.formats.rig import default_rig, parse_rig, rig_to_dict
from ringscan.pipeline.formats.scan import (
    Scan,
    View,
    as_camera2,
    load_scan,
    read_view_frame,
    read_view_frames,
    save_scan,
)

GRAY = {"codec": "gray-rings", "width": 1024, "height": 768, "center": [511.5, 383.5], "rho0": 8, "pitch": 4,
        "bits": 3, "sector_bits": 2, "angle_steps": 0}
W, H = 40, 30


def test_bit_replication_is_exact_on_every_12_bit_value():
    v = np.arange(4096, dtype=np.uint16)
    w = expand_frame_bits(v.copy(), 12).astype(np.int64)
    assert w[0] == 0 and w[-1] == 65535
    assert np.all(np.diff(w) > 0)  # strictly monotonic: no two levels merge
    vi = v.astype(np.int64)
    assert np.array_equal(w, (vi << 4) | (vi >> 8))
    # the replication is v * 65535 / 4095 rounded, give or take one level of 65536
    assert np.abs(w - vi * 65535 / 4095).max() <= 1.0
    # every 16-bit value v16 whose top 12 bits are v lies within 15 levels of v's replication
    assert np.all(np.abs(w - (vi << 4)) <= 15)


@pytest.mark.parametrize("bits", range(9, 17))
def test_bit_replication_spans_the_range_at_every_depth(bits):
    v = np.arange(1 << bits, dtype=np.uint16)
    w = expand_frame_bits(v.copy(), bits).astype(np.int64)
    assert w[0] == 0 and w[-1] == 65535 and np.all(np.diff(w) > 0)
    assert np.abs(w - v.astype(np.int64) * 65535 / ((1 << bits) - 1)).max() <= 1.0


def test_bit_replication_works_in_place_on_a_stack_and_refuses_other_input():
    rng = np.random.default_rng(1)
    a = rng.integers(0, 1024, (3, 5, 7)).astype(np.uint16)
    b = a.copy()
    assert expand_frame_bits(b, 10) is b
    ai = a.astype(np.int64)
    assert np.array_equal(b, (ai << 6) | (ai >> 4))
    with pytest.raises(ValueError, match="uint16"):
        expand_frame_bits(a.astype(np.uint8), 12)
    for bad in (8, 17, True, 12.0):
        with pytest.raises(ValueError, match="bits"):
            expand_frame_bits(a.copy(), bad)


def _rig(camera2: bool):
    d = rig_to_dict(default_rig())
    d["camera"].update(width=W, height=H)
    if camera2:
        d["camera2"] = {**d["camera"], "t": [d["camera"]["t"][0] + 60.0, *d["camera"]["t"][1:]]}
    return parse_rig(d)


def _write(folder, full: np.ndarray, *, bits: int | None, shift: int, camera2: np.ndarray | None = None):
    """A scan of ``full`` (n, H, W) uint16 frames stored right-shifted by ``shift`` (a
    (16 - shift)-bit camera's values), scan.json's frame_bits ``bits`` (None: absent)."""
    spec = parse_patterns(GRAY)
    names = frame_names(spec)

    def frames(stack, sub):
        out = {}
        for n, img in zip(names, stack):
            rel = f"view_000/{sub}{n}.png"
            write_image(folder / rel, img >> shift)
            out[n] = rel
        return out

    v2 = None if camera2 is None else View("view_000", 0.0, frames(camera2, "cam2/"))
    scan = Scan(folder=folder, rig=_rig(camera2 is not None), patterns=spec,
                views=(View("view_000", 0.0, frames(full, ""), camera2=v2),), frame_bits=bits)
    save_scan(scan)
    return load_scan(folder)


def _stack(seed: int) -> np.ndarray:
    n = len(frame_names(parse_patterns(GRAY)))
    return np.random.default_rng(seed).integers(0, 65536, (n, H, W), dtype=np.uint16)


def test_12_bit_frames_read_scaled_to_within_15_levels_of_the_16_bit_original(tmp_path):
    full, full2 = _stack(0), _stack(1)
    scan = _write(tmp_path, full, bits=12, shift=4, camera2=full2)
    assert scan.frame_bits == 12 and json.loads(scan.path.read_text())["frame_bits"] == 12
    for s, v, ref in ((scan, scan.views[0], full), (as_camera2(scan), scan.views[0].camera2, full2)):
        st = read_view_frames(s, v)
        assert st.dtype == np.uint16
        r = ref.astype(np.int64)
        assert np.array_equal(st, ((r >> 4) << 4) | (r >> 12))  # the stored 12 bits, replicated
        assert np.abs(st.astype(np.int64) - r).max() <= 15
        assert np.array_equal(read_view_frames(s, v, raw=True), ref >> 4)
        assert np.array_equal(read_view_frame(s, v, "white"), st[0])
        assert np.array_equal(read_view_frame(s, v, "white", raw=True), ref[0] >> 4)


def test_packed_frames_are_scaled_alike_and_pack_keeps_the_stored_values(tmp_path):
    full = _stack(2)
    scan = _write(tmp_path, full, bits=10, shift=6)
    want = read_view_frames(scan, scan.views[0])
    assert np.array_equal(want, expand_frame_bits(full >> 6, 10))
    pack_scan(tmp_path)
    packed = load_scan(tmp_path)
    assert packed.views[0].packed is not None and packed.frame_bits == 10
    assert np.array_equal(read_view_frames(packed, packed.views[0], raw=True), full >> 6)  # stored as captured
    assert np.array_equal(read_view_frames(packed, packed.views[0]), want)
    assert np.array_equal(read_view_frame(packed, packed.views[0], "black"), want[1])
    unpack_scan(tmp_path)
    back = load_scan(tmp_path)
    assert back.views[0].packed is None and back.frame_bits == 10
    assert np.array_equal(read_image(back.frame_path(back.views[0], "white")), full[0] >> 6)


def test_a_value_above_the_range_is_refused_naming_the_frame(tmp_path):
    full = _stack(3)
    scan = _write(tmp_path, full, bits=12, shift=4)
    p = scan.frame_path(scan.views[0], "gray_1")
    img = read_image(p)
    img[3, 4] = 5000
    write_image(p, img)
    with pytest.raises(FormatError) as e:
        read_view_frames(scan, scan.views[0])
    msg = str(e.value)
    assert str(p) in msg and "holds 5000, above the 12-bit range frame_bits says (4095)" in msg and "\n" not in msg
    with pytest.raises(FormatError, match="holds 5000"):
        read_view_frame(scan, scan.views[0], "gray_1")
    assert read_view_frames(scan, scan.views[0], raw=True)[frame_names(scan.patterns).index("gray_1"), 3, 4] == 5000
    # packed: the frame's chunk file is named
    pack_scan(tmp_path)
    packed = load_scan(tmp_path)
    info = open_store(packed.folder / packed.views[0].packed)
    with pytest.raises(FormatError) as e:
        read_view_frames(packed, packed.views[0])
    assert str(info.chunk_path(info.index("gray_1"))) in str(e.value) and "holds 5000" in str(e.value)


def test_full_16_bit_and_8_bit_scans_read_as_before(tmp_path):
    full = _stack(4)
    for bits in (None, 16):
        folder = tmp_path / f"s{bits}"
        scan = _write(folder, full, bits=bits, shift=0)
        assert np.array_equal(read_view_frames(scan, scan.views[0]), full)
        assert ("frame_bits" in json.loads(scan.path.read_text())) == (bits is not None)
    eight = (full >> 8).astype(np.uint8)
    spec = parse_patterns(GRAY)
    frames = {}
    for n, img in zip(frame_names(spec), eight):
        write_image(tmp_path / "s8" / f"{n}.png", img)
        frames[n] = f"{n}.png"
    save_scan(Scan(folder=tmp_path / "s8", rig=_rig(False), patterns=spec, views=(View("v", 0.0, frames),),
                   frame_bits=8))
    scan = load_scan(tmp_path / "s8")
    assert scan.frame_bits == 8 and np.array_equal(read_view_frames(scan, scan.views[0]), eight)


@pytest.mark.parametrize("value", [0, 7, 17, "12", True, 12.0, None])
def test_bad_frame_bits_is_one_line_naming_scan_json(tmp_path, value):
    _write(tmp_path, _stack(5), bits=12, shift=4)
    p = tmp_path / "scan.json"
    d = json.loads(p.read_text())
    d["frame_bits"] = value
    p.write_text(json.dumps(d))
    if value is None:  # null: as absent
        assert load_scan(tmp_path).frame_bits is None
        return
    with pytest.raises(FormatError) as e:
        load_scan(tmp_path)
    msg = str(e.value)
    assert msg.startswith(str(p)) and "frame_bits: expected a whole number" in msg and "\n" not in msg


def test_frame_bits_that_do_not_match_the_frames_bit_depth_are_refused(tmp_path):
    scan = _write(tmp_path / "a", _stack(6), bits=8, shift=4)  # 16-bit files, frame_bits 8
    with pytest.raises(FormatError, match=r"frame is 16-bit, but frame_bits in .*scan.json says 8") as e:
        read_view_frames(scan, scan.views[0])
    assert str(scan.frame_path(scan.views[0], "white")) in str(e.value)
    spec = parse_patterns(GRAY)
    frames = {}
    for n in frame_names(spec):
        write_image(tmp_path / "b" / f"{n}.png", np.full((H, W), 9, np.uint8))
        frames[n] = f"{n}.png"
    save_scan(Scan(folder=tmp_path / "b", rig=_rig(False), patterns=spec, views=(View("v", 0.0, frames),),
                   frame_bits=12))
    scan = load_scan(tmp_path / "b")
    with pytest.raises(FormatError, match=r"frame is 8-bit, but frame_bits in .*scan.json says 12"):
        read_view_frames(scan, scan.views[0])
    with pytest.raises(FormatError, match="8-bit"):
        read_view_frame(scan, scan.views[0], "white")


def test_the_decoded_codec_takes_no_frame_bits_below_16(tmp_path):
    spec = parse_patterns({"codec": "decoded", "width": 1024, "height": 768, "center": [511.5, 383.5], "rho0": 0.0,
                           "pitch": 1.0, "sector_bits": 4})
    frames = {}
    for n in frame_names(spec):
        write_image(tmp_path / f"{n}.png", np.zeros((H, W), np.uint16))
        frames[n] = f"{n}.png"
    save_scan(Scan(folder=tmp_path, rig=_rig(False), patterns=spec, views=(View("v", 0.0, frames),), frame_bits=12))
    with pytest.raises(FormatError, match="frame_bits: 12, but the decoded codec's frames are projector coordinates"):
        load_scan(tmp_path)
