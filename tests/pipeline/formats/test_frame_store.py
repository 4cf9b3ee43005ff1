"""The packed frame store: bit-exact round trips, a Zarr v3 array other tools read, damage named by file."""

import json

import numpy as np
import pytest

from ringscan.pipeline.formats import frame_store as fs
from ringscan.pipeline.formats.errors import FormatError

NAMES = ["white", "black", "gray_0", "gray_0_inv", "phase_0"]


def _frames(dtype, n=len(NAMES), h=37, w=53, seed=1):
    rng = np.random.default_rng(seed)
    hi = np.iinfo(dtype).max
    a = rng.integers(0, hi + 1, size=(n, h, w), dtype=np.int64).astype(dtype)
    a[0, 0, :3] = (0, hi, hi // 2 + 1)  # both ends of the range
    return a


@pytest.mark.parametrize("dtype", [np.uint8, np.uint16])
def test_round_trip_is_bit_exact(tmp_path, dtype):
    a = _frames(dtype)
    info = fs.write_store(tmp_path / "v" / fs.STORE_NAME, a, NAMES)
    back = fs.read_store(tmp_path / "v" / fs.STORE_NAME)
    assert back.dtype == dtype and back.shape == a.shape and np.array_equal(back, a)
    assert info.names == tuple(NAMES)
    # a subset in another order, decoded on two threads
    sub = fs.read_store(info, ["gray_0", "white"], threads=2)
    assert np.array_equal(sub, a[[2, 0]])
    assert not [p for p in (tmp_path / "v").iterdir() if p.name.startswith(".")]  # no temporaries left


@pytest.mark.parametrize("cname,shuffle", [("zstd", "bitshuffle"), ("lz4", "shuffle"), ("lz4hc", "bitshuffle"),
                                           ("blosclz", "noshuffle"), ("zlib", "bitshuffle")])
def test_stores_written_with_any_blosc_codec_read_back(tmp_path, monkeypatch, cname, shuffle):
    """The reader follows each chunk's own header: stores written with other Blosc settings (an
    older ringscan's, another tool's) read bit-exactly with today's."""
    a = _frames(np.uint8)
    monkeypatch.setattr(fs, "BLOSC", {"cname": cname, "clevel": 9, "shuffle": shuffle, "blocksize": 1 << 16})
    fs.write_store(tmp_path / "v.zarr", a, NAMES)
    meta = json.loads((tmp_path / "v.zarr" / "zarr.json").read_text())
    assert meta["codecs"][1]["configuration"]["cname"] == cname
    # the chunks hold what zarr.json says (Blosc's header: flags bit 0 byte-shuffle, bit 2 bit-shuffle)
    flags = (tmp_path / "v.zarr" / "c" / "0" / "0" / "0").read_bytes()[2]
    assert (flags & 1, flags >> 2 & 1) == {"noshuffle": (0, 0), "shuffle": (1, 0), "bitshuffle": (0, 1)}[shuffle]
    monkeypatch.undo()
    assert fs.BLOSC["cname"] == "zstd"
    assert np.array_equal(fs.read_store(tmp_path / "v.zarr"), a)


def test_zarr_python_reads_the_store_and_writes_one_we_read(tmp_path):
    zarr = pytest.importorskip("zarr")
    a = _frames(np.uint16)
    fs.write_store(tmp_path / "ours.zarr", a, NAMES)
    z = zarr.open_array(tmp_path / "ours.zarr", mode="r")
    assert np.array_equal(z[:], a) and z.attrs["ringscan"]["frames"] == NAMES
    # a store written by zarr-python with the same layout reads back through ringscan's reader
    z2 = zarr.create_array(tmp_path / "theirs.zarr", shape=a.shape, chunks=(1,) + a.shape[1:], dtype="uint16",
                           serializer=zarr.codecs.BytesCodec(endian="little"),
                           compressors=[zarr.codecs.BloscCodec(cname="lz4", clevel=3, shuffle="shuffle"),
                                        zarr.codecs.Crc32cCodec()],
                           attributes={"ringscan": {"format": fs.STORE_FORMAT, "frames": NAMES}}, fill_value=0)
    z2[:] = a
    assert np.array_equal(fs.read_store(tmp_path / "theirs.zarr"), a)


def test_damaged_chunk_and_missing_chunk_are_named(tmp_path):
    a = _frames(np.uint8)
    info = fs.write_store(tmp_path / "s.zarr", a, NAMES)
    chunk = info.chunk_path(2)
    raw = bytearray(chunk.read_bytes())
    raw[len(raw) // 2] ^= 0x40
    chunk.write_bytes(bytes(raw))
    with pytest.raises(FormatError, match="CRC32C") as e:
        fs.read_store(info)
    assert e.value.path == str(chunk)
    # the frames before and after it still read
    assert np.array_equal(fs.read_store(info, ["white", "phase_0"]), a[[0, 4]])
    info.chunk_path(4).unlink()
    with pytest.raises(FormatError, match="frame missing") as e:
        fs.read_store(info, ["phase_0"])
    assert e.value.path == str(info.chunk_path(4))
    assert fs.missing_frames(info) == ["phase_0"]


def test_chunk_of_another_size_is_refused_even_with_a_good_checksum(tmp_path):
    a = _frames(np.uint8)
    info = fs.write_store(tmp_path / "s.zarr", a, NAMES)
    other = fs.write_store(tmp_path / "t.zarr", _frames(np.uint8, h=20), NAMES)
    info.chunk_path(1).write_bytes(other.chunk_path(1).read_bytes())
    with pytest.raises(FormatError, match="not one 53x37 uint8 frame"):
        fs.read_store(info)


@pytest.mark.parametrize("edit, match", [
    (lambda d: d.update(shape=[5, 37]), "shape: expected"),
    (lambda d: d.update(shape=[6, 37, 53]), "frames: expected 6 distinct"),
    (lambda d: d.update(data_type="float32"), "data_type"),
    (lambda d: d["chunk_grid"]["configuration"].update(chunk_shape=[2, 37, 53]), "one chunk per frame"),
    (lambda d: d["codecs"].pop(), "codecs: expected bytes, blosc, crc32c"),
    (lambda d: d["attributes"]["ringscan"].update(frames=NAMES[:-1] + ["white"]), "distinct frame names"),
    (lambda d: d.update(zarr_format=2), "not a Zarr v3 array"),
])
def test_bad_metadata_is_named(tmp_path, edit, match):
    info = fs.write_store(tmp_path / "s.zarr", _frames(np.uint8), NAMES)
    meta = info.path / "zarr.json"
    d = json.loads(meta.read_text())
    edit(d)
    meta.write_text(json.dumps(d))
    with pytest.raises(FormatError, match=match) as e:
        fs.read_store(info.path)
    assert e.value.path == str(meta)


def test_a_failed_write_leaves_the_old_store_and_no_temporary(tmp_path, monkeypatch):
    a = _frames(np.uint8)
    path = tmp_path / "s.zarr"
    fs.write_store(path, a, NAMES)
    calls = []

    def failing(info, name, img, real=fs.write_frame):
        calls.append(name)
        if len(calls) == 3:
            raise KeyboardInterrupt
        real(info, name, img)

    monkeypatch.setattr(fs, "write_frame", failing)
    with pytest.raises(KeyboardInterrupt):
        fs.write_store(path, a[::-1].copy(), NAMES)
    assert np.array_equal(fs.read_store(path), a)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["s.zarr"]


def test_frames_appended_one_by_one_resume(tmp_path):
    a = _frames(np.uint16)
    info = fs.create_store(tmp_path / "s.zarr", NAMES, height=37, width=53, dtype=np.uint16)
    for n, img in zip(NAMES[:2], a[:2]):
        fs.write_frame(info, n, img)
    again = fs.create_store(tmp_path / "s.zarr", NAMES, height=37, width=53, dtype=np.uint16)  # a resumed capture
    assert fs.missing_frames(again) == NAMES[2:]
    for n, img in zip(NAMES[2:], a[2:]):
        fs.write_frame(again, n, img)
    assert np.array_equal(fs.read_store(again), a)
    with pytest.raises(FormatError, match="a different frame store"):
        fs.create_store(tmp_path / "s.zarr", NAMES, height=37, width=53, dtype=np.uint8)


def test_metadata_nested_too_deeply_or_of_frames_too_large_is_refused_before_decoding(tmp_path):
    info = fs.write_store(tmp_path / "s.zarr", _frames(np.uint8), NAMES)
    meta = info.path / "zarr.json"
    good = meta.read_text()
    meta.write_text("[" * 100000)  # before: RecursionError out of json.loads
    with pytest.raises(FormatError, match=r"zarr.json: not valid JSON \(nested too deeply\)") as e:
        fs.read_store(info.path)
    assert e.value.path == str(meta)
    # 30000x30000 frames (900 megapixels), within 65536 a side: refused as an image header of that size is,
    # before a chunk is read (before: decoded into 900 MB a frame)
    d = json.loads(good)
    d["shape"] = [len(NAMES), 30000, 30000]
    d["chunk_grid"]["configuration"]["chunk_shape"] = [1, 30000, 30000]
    meta.write_text(json.dumps(d))
    with pytest.raises(FormatError) as e:
        fs.open_store(info.path)
    assert str(e.value) == (f"{meta}: frames are 30000x30000 (900 megapixels): larger than ringscan reads (at most "
                            "65536 px a side, 200 megapixels)")


def test_a_fifo_in_place_of_a_chunk_or_the_metadata_is_refused_without_blocking(tmp_path):
    import os

    from tests.support.threads import in_thread

    info = fs.write_store(tmp_path / "s.zarr", _frames(np.uint8), NAMES)
    chunk = info.chunk_path(2)
    chunk.unlink()
    os.mkfifo(chunk)
    got = in_thread(lambda: fs.read_store(info))  # before: blocked forever in open()
    if got == "hung":
        with open(chunk, "wb"):
            pass
    assert isinstance(got, FormatError), got
    assert str(got) == f"{chunk}: frame chunk is a pipe (FIFO), not a regular file (damaged store)"
    with pytest.raises(FormatError, match="frame chunk is a pipe"):
        fs.check_chunk_files(info, NAMES)
    meta = info.path / "zarr.json"
    meta.unlink()
    os.mkfifo(meta)
    got = in_thread(lambda: fs.open_store(info.path))
    if got == "hung":
        with open(meta, "wb"):
            pass
    assert isinstance(got, FormatError) and str(got).startswith(f"{meta}: is a pipe (FIFO)"), got
