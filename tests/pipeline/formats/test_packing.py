"""Packing a scan's frames into stores and back: lossless, checked before removal, resumable."""

import json

import cv2
import numpy as np
import pytest

from ringscan.pipeline.formats import frame_store
from ringscan.pipeline.formats.errors import FormatError
from ringscan.pipeline.formats.images import write_image
from ringscan.pipeline.formats.packing import pack_scan, unpack_scan
from ringscan.pipeline.formats.scan import SCAN_FORMAT, SCAN_FORMAT_PACKED, load_scan, read_view_frame, read_view_frames
from tests.support.noise_scan import H, W, noise_scan


def _files(folder):
    return sorted(p.relative_to(folder).as_posix() for p in folder.rglob("*") if p.is_file())


def _check_frames(folder, truth):
    scan = load_scan(folder)
    for k, v in enumerate(scan.views):
        names = list(v.frames)
        got = read_view_frames(scan, v, names, threads=1)
        assert all(np.array_equal(g, truth[(k, n)]) for g, n in zip(got, names))


@pytest.mark.parametrize("dtype, ext", [(np.uint8, "png"), (np.uint16, "png"), (np.uint16, "tiff")])
def test_pack_and_unpack_are_lossless(tmp_path, dtype, ext):
    truth = noise_scan(tmp_path, dtype=dtype, ext=ext)
    r = pack_scan(tmp_path)
    assert r.converted == ["view_0", "view_1"] and r.removed == 2 * len(truth) // 2
    d = json.loads((tmp_path / "scan.json").read_text())
    assert d["format"] == SCAN_FORMAT_PACKED
    names = list(load_scan(tmp_path).views[1].frames)
    assert d["views"][1]["packed"] == {"store": "view_1/frames.zarr", "frames": names}
    assert not [f for f in _files(tmp_path) if f.endswith(("." + ext))]  # originals gone
    _check_frames(tmp_path, truth)
    scan = load_scan(tmp_path)
    assert np.array_equal(read_view_frame(scan, scan.views[1], "gray_1"), truth[(1, "gray_1")])
    assert pack_scan(tmp_path).already == ["view_0", "view_1"]  # nothing to do again
    r = unpack_scan(tmp_path, image_format=ext)
    assert r.converted == ["view_0", "view_1"]
    assert json.loads((tmp_path / "scan.json").read_text())["format"] == SCAN_FORMAT
    assert not (tmp_path / "view_0" / "frames.zarr").exists()
    _check_frames(tmp_path, truth)


def test_keep_leaves_the_originals_and_a_later_pack_removes_them_after_comparing(tmp_path):
    # --keep leaves the state a pack killed after rewriting scan.json leaves: store + old files
    truth = noise_scan(tmp_path, views=1)
    before = {f: (tmp_path / f).read_bytes() for f in _files(tmp_path) if f.endswith(".png")}
    pack_scan(tmp_path, keep=True)
    assert {f: (tmp_path / f).read_bytes() for f in before} == before
    assert load_scan(tmp_path).views[0].packed == "view_0/frames.zarr"
    # a leftover that differs from its frame is named and kept
    bad = tmp_path / "view_0" / "gray_2.png"
    write_image(bad, truth[(0, "gray_2")] ^ 1)
    with pytest.raises(FormatError, match="differs from frame 'gray_2'") as e:
        pack_scan(tmp_path)
    assert e.value.path == str(bad) and bad.is_file()
    write_image(bad, truth[(0, "gray_2")])
    r = pack_scan(tmp_path)
    assert r.removed == len(before) and not [f for f in _files(tmp_path) if f.endswith(".png")]
    _check_frames(tmp_path, truth)


def test_a_killed_pack_leaves_the_originals_and_resumes(tmp_path, monkeypatch):
    truth = noise_scan(tmp_path)
    scan_json = (tmp_path / "scan.json").read_bytes()
    before = _files(tmp_path)
    calls = []

    def killed(info, name, img, real=frame_store.write_frame):
        calls.append(name)
        if len(calls) == 20:  # in the second view
            raise KeyboardInterrupt
        real(info, name, img)

    monkeypatch.setattr(frame_store, "write_frame", killed)
    with pytest.raises(KeyboardInterrupt):
        pack_scan(tmp_path)
    scan = load_scan(tmp_path)
    assert scan.views[0].packed and scan.views[1].packed is None  # view 0 done, view 1 untouched
    assert all((tmp_path / r).is_file() for r in scan.views[1].frames.values())
    assert [f for f in _files(tmp_path) if f.startswith("view_1/")] == [f for f in before if f.startswith("view_1/")]
    monkeypatch.undo()
    r = pack_scan(tmp_path)
    assert r.converted == ["view_1"] and r.already == ["view_0"]
    _check_frames(tmp_path, truth)
    assert scan_json != (tmp_path / "scan.json").read_bytes()


def test_a_bad_frame_is_named_and_nothing_is_written(tmp_path):
    noise_scan(tmp_path, views=1)
    bad = tmp_path / "view_0" / "sector_1.png"
    bad.write_bytes(bad.read_bytes()[:100])
    before = {f: (tmp_path / f).read_bytes() for f in _files(tmp_path)}
    with pytest.raises(FormatError) as e:
        pack_scan(tmp_path)
    assert e.value.path == str(bad)
    assert {f: (tmp_path / f).read_bytes() for f in _files(tmp_path)} == before


def test_a_frame_name_that_is_no_file_name_is_refused_before_anything_is_written(tmp_path):
    noise_scan(tmp_path, views=1)
    d = json.loads((tmp_path / "scan.json").read_text())
    d["views"][0]["frames"]["sub/extra"] = d["views"][0]["frames"]["white"]
    (tmp_path / "scan.json").write_text(json.dumps(d))
    before = {f: (tmp_path / f).read_bytes() for f in _files(tmp_path)}
    with pytest.raises(FormatError, match="frame name: 'sub/extra' is not a folder-safe name"):
        pack_scan(tmp_path)
    assert {f: (tmp_path / f).read_bytes() for f in _files(tmp_path)} == before


def test_colour_png_is_refused(tmp_path):
    noise_scan(tmp_path, views=1)
    p = tmp_path / "view_0" / "white.png"
    cv2.imwrite(str(p), np.zeros((H, W, 3), np.uint8))
    with pytest.raises(FormatError, match="colour frame") as e:
        pack_scan(tmp_path)
    assert e.value.path == str(p)


def test_packed_scan_json_is_checked(tmp_path):
    truth = noise_scan(tmp_path, views=1)
    pack_scan(tmp_path)
    src = tmp_path / "scan.json"
    d = json.loads(src.read_text())

    def bad(edit, match, path=src):
        e2 = json.loads(json.dumps(d))
        edit(e2)
        src.write_text(json.dumps(e2))
        with pytest.raises(FormatError, match=match) as e:
            scan = load_scan(tmp_path)
            read_view_frames(scan, scan.views[0])
        assert e.value.path == str(path)

    bad(lambda e: e.update(format=SCAN_FORMAT), "packed frames need format")
    bad(lambda e: e["views"][0].update(frames={}), "both frames and packed")
    bad(lambda e: e["views"][0]["packed"].update(store="../x.zarr"), "leaves the scan folder")
    bad(lambda e: e["views"][0]["packed"].update(frames=["../../evil"]), r"packed.frames\[0\]: '../../evil' is not")
    bad(lambda e: e["views"][0]["packed"].update(store="view_0/other.zarr"), "frame store of view_0 not found",
        path=tmp_path / "view_0" / "other.zarr")
    names = d["views"][0]["packed"]["frames"]
    bad(lambda e: e["views"][0]["packed"].update(frames=names[::-1]), "do not match scan.json's list",
        path=tmp_path / "view_0" / "frames.zarr" / "zarr.json")
    src.write_text(json.dumps(d))
    d2 = json.loads(src.read_text())
    d2["rig"]["camera"].update(width=W + 2)
    src.write_text(json.dumps(d2))
    with pytest.raises(FormatError, match=f"frames are {W}x{H}, but the camera is {W + 2}x{H}"):
        scan = load_scan(tmp_path)
        read_view_frames(scan, scan.views[0])
    src.write_text(json.dumps(d))
    _check_frames(tmp_path, truth)


def test_a_fifo_chunk_stops_unpack_and_a_later_pack_without_blocking(tmp_path):
    import os

    from tests.support.threads import in_thread

    noise_scan(tmp_path, views=1)
    pack_scan(tmp_path, keep=True)  # the images stay beside the store: the next pack compares them
    chunk = tmp_path / "view_0" / "frames.zarr" / "c" / "2" / "0" / "0"
    chunk.unlink()
    os.mkfifo(chunk)
    before = {f: (tmp_path / f).read_bytes() for f in _files(tmp_path)}
    for run in (lambda: pack_scan(tmp_path), lambda: unpack_scan(tmp_path)):
        got = in_thread(run)  # before: both blocked forever opening the FIFO
        if got == "hung":
            with open(chunk, "wb"):
                pass
        assert isinstance(got, FormatError) and got.path == str(chunk), got
        assert "frame chunk is a pipe (FIFO), not a regular file" in str(got)
        assert {f: (tmp_path / f).read_bytes() for f in _files(tmp_path)} == before


@pytest.mark.parametrize("ext", ["tiff", "jpg", "bmp"])
def test_a_colour_frame_of_any_format_is_refused_and_kept(tmp_path, ext):
    """Before: only PNG was checked; a colour TIFF or JPEG was packed as grey and the original removed."""
    noise_scan(tmp_path, views=1)
    d = json.loads((tmp_path / "scan.json").read_text())
    p = tmp_path / "view_0" / f"white.{ext}"
    colour = np.zeros((H, W, 3), np.uint8)
    colour[..., 2] = 200
    cv2.imwrite(str(p), colour)
    d["views"][0]["frames"]["white"] = f"view_0/white.{ext}"
    (tmp_path / "scan.json").write_text(json.dumps(d))
    before = {f: (tmp_path / f).read_bytes() for f in _files(tmp_path)}
    with pytest.raises(FormatError, match="colour frame: a packed store keeps frames as ringscan reads them") as e:
        pack_scan(tmp_path)
    assert e.value.path == str(p)
    assert {f: (tmp_path / f).read_bytes() for f in _files(tmp_path)} == before
    cv2.imwrite(str(p), colour[..., 2])  # the same frame in grey packs
    assert pack_scan(tmp_path).converted == ["view_0"]


def test_two_views_naming_the_same_files_both_pack(tmp_path):
    """Before: the first view's pack removed the files the second view names; the scan then did not load."""
    truth = noise_scan(tmp_path, views=2)
    d = json.loads((tmp_path / "scan.json").read_text())
    d["views"][1]["frames"] = dict(d["views"][0]["frames"])  # view_1's own files: named by no view now
    (tmp_path / "scan.json").write_text(json.dumps(d))
    r = pack_scan(tmp_path)
    assert r.converted == ["view_0", "view_1"] and r.removed == len(d["views"][0]["frames"])
    scan = load_scan(tmp_path)
    assert [v.packed for v in scan.views] == ["view_0/frames.zarr", "view_1/frames.zarr"]
    assert not [f for f in _files(tmp_path) if f.startswith("view_0/") and f.endswith(".png")]
    for v in scan.views:
        got = read_view_frames(scan, v, list(v.frames))
        assert all(np.array_equal(g, truth[(0, n)]) for g, n in zip(got, v.frames))


def test_a_killed_pack_between_two_views_naming_the_same_files_resumes(tmp_path, monkeypatch):
    truth = noise_scan(tmp_path, views=2)
    d = json.loads((tmp_path / "scan.json").read_text())
    d["views"][1]["frames"] = dict(d["views"][0]["frames"])
    (tmp_path / "scan.json").write_text(json.dumps(d))
    calls = []

    def killed(info, name, img, real=frame_store.write_frame):
        calls.append(name)
        if len(calls) == len(d["views"][0]["frames"]) + 1:  # the second view's first frame
            raise KeyboardInterrupt
        real(info, name, img)

    monkeypatch.setattr(frame_store, "write_frame", killed)
    with pytest.raises(KeyboardInterrupt):
        pack_scan(tmp_path)
    monkeypatch.undo()
    assert all((tmp_path / r).is_file() for r in d["views"][1]["frames"].values())  # still needed: kept
    r = pack_scan(tmp_path)
    assert r.already == ["view_0"] and r.converted == ["view_1"]
    scan = load_scan(tmp_path)
    got = read_view_frames(scan, scan.views[1], list(scan.views[1].frames))
    assert all(np.array_equal(g, truth[(0, n)]) for g, n in zip(got, scan.views[1].frames))
    assert not [f for f in _files(tmp_path) if f.startswith("view_0/") and f.endswith(".png")]


def test_unpack_refuses_a_link_in_place_of_a_frame_before_writing(tmp_path):
    """Before: a frame file that was a link out of the scan (holding the same frame) was kept, and the scan then
    refused to load (a path through a link out of the folder)."""
    truth = noise_scan(tmp_path / "scan", views=2)
    folder = tmp_path / "scan"
    pack_scan(folder)
    outside = tmp_path / "white.png"
    write_image(outside, truth[(1, "white")])
    link = folder / "view_1" / "white.png"
    link.symlink_to(outside)
    before = {f: (folder / f).read_bytes() for f in _files(folder)}
    with pytest.raises(FormatError) as e:
        unpack_scan(folder)
    assert str(e.value) == (f"{link}: is a symbolic link (to {outside}) in the way of frame 'white' of the store "
                            "view_1/frames.zarr: remove it, then unpack again")
    assert {f: (folder / f).read_bytes() for f in _files(folder)} == before  # view_0 not unpacked either
    link.unlink()
    assert unpack_scan(folder).converted == ["view_0", "view_1"]
    _check_frames(folder, truth)


def test_unpack_removes_what_killed_runs_left(tmp_path, monkeypatch):
    """A store whose chunks a killed deletion removed (zarr.json left): before, every rerun failed (`frame missing
    from the frame store`) though the frames were all there; hidden temporary images of a killed write were never
    removed; a store renamed for deletion is removed too."""
    import shutil

    truth = noise_scan(tmp_path, views=1)
    pack_scan(tmp_path)
    store = tmp_path / "view_0" / "frames.zarr"
    saved = tmp_path.parent / f"{tmp_path.name}_store"
    shutil.copytree(store, saved)
    unpack_scan(tmp_path)  # the images are written and scan.json names them
    shutil.copytree(saved, store)
    shutil.rmtree(store / "c" / "0")  # a deletion killed half-way: zarr.json and some chunks left
    shutil.rmtree(store / "c" / "3")
    dead = 2 ** 22 + 12345  # a process id that is not running (above the default pid_max)
    tmp_image = tmp_path / "view_0" / f".white.png.{dead}-0123abcd.tmp.png"
    tmp_image.write_bytes(b"half a png")
    renamed = tmp_path / "view_0" / f".frames.zarr.{dead}-89abcdef.tmp"
    shutil.copytree(saved, renamed)
    r = unpack_scan(tmp_path)
    assert r.already == ["view_0"] and r.removed == 1
    assert not store.exists() and not tmp_image.exists() and not renamed.exists()
    _check_frames(tmp_path, truth)
