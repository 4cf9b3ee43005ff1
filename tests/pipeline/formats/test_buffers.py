"""Frame stacks reused from view to view: the same memory handed back, the same frames read into it."""

import threading

import numpy as np
import pytest

from ringscan.pipeline.formats import frame_store as fs
from ringscan.pipeline.formats.buffers import FrameBuffers
from ringscan.pipeline.formats.packing import pack_scan
from ringscan.pipeline.formats.scan import load_scan, read_view_frames
from tests.support.noise_scan import noise_scan


def test_a_given_stack_is_taken_again_and_the_pool_stays_bounded():
    pool = FrameBuffers(keep=2)
    a = pool.take((3, 4, 5), np.uint8)
    assert a.shape == (3, 4, 5) and a.dtype == np.uint8 and a.flags.c_contiguous
    pool.give(a)
    assert pool.take((3, 4, 5), np.uint8) is a
    # another shape or dtype is a new array; the one given back stays for its own kind
    pool.give(a)
    b = pool.take((3, 4, 5), np.uint16)
    c = pool.take((2, 4, 5), np.uint8)
    assert b is not a and c is not a and b.dtype == np.uint16 and c.shape == (2, 4, 5)
    assert pool.take((3, 4, 5), np.uint8) is a
    # at most `keep` kept: the oldest goes first; a stack given twice is kept once
    pool.give(a)
    pool.give(a)
    pool.give(b)
    pool.give(c)
    assert pool.take((3, 4, 5), np.uint8) is not a
    assert pool.take((3, 4, 5), np.uint16) is b and pool.take((2, 4, 5), np.uint8) is c
    # views of other memory are never kept (their owner may still use it), nor is anything with keep=0
    big = np.empty((6, 4, 5), np.uint8)
    pool.give(big[:3])
    assert pool.take((3, 4, 5), np.uint8).base is None
    none = FrameBuffers(keep=0)
    none.give(a)
    assert none.take((3, 4, 5), np.uint8) is not a
    with pytest.raises(ValueError):
        FrameBuffers(keep=-1)


def test_the_pool_keeps_no_more_bytes_than_asked():
    """A camera of many large frames: the pool keeps what fits in its bound, newest first, and
    nothing larger than the bound (a worker keeps within the memory the user lets it keep)."""
    pool = FrameBuffers(keep=2, max_bytes=150)
    a, b = np.empty((1, 10, 10), np.uint8), np.empty((1, 10, 10), np.uint8)
    pool.give(a)
    pool.give(b)  # 200 bytes > 150: the older goes
    assert pool.take((1, 10, 10), np.uint8) is b and pool.take((1, 10, 10), np.uint8) is not a
    big = np.empty((2, 10, 10), np.uint8)
    pool.give(big)
    assert pool.take((2, 10, 10), np.uint8) is not big
    with pytest.raises(ValueError):
        FrameBuffers(max_bytes=-1)


def test_threads_never_take_the_same_stack():
    pool = FrameBuffers(keep=8)
    for _ in range(8):
        pool.give(np.empty((2, 3, 4), np.uint8))
    got, lock = [], threading.Lock()

    def take():
        a = pool.take((2, 3, 4), np.uint8)
        with lock:
            got.append(a)

    threads = [threading.Thread(target=take) for _ in range(8)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert len({id(a) for a in got}) == 8


def test_read_store_decodes_into_the_given_stack(tmp_path):
    rng = np.random.default_rng(5)
    frames = rng.integers(0, 256, size=(3, 7, 9), dtype=np.int64).astype(np.uint8)
    info = fs.write_store(tmp_path / fs.STORE_NAME, frames, ["a", "b", "c"])
    out = np.zeros((2, 7, 9), np.uint8)
    assert fs.read_store(info, ["c", "a"], out=out) is out
    assert np.array_equal(out, frames[[2, 0]])
    for bad in (np.zeros((3, 7, 9), np.uint8), np.zeros((2, 7, 9), np.uint16), np.zeros((2, 9, 7), np.uint8),
                np.zeros((2, 7, 18), np.uint8)[:, :, ::2]):
        with pytest.raises(ValueError, match="out must be"):
            fs.read_store(info, ["c", "a"], out=bad)


@pytest.mark.parametrize("packed", [False, True])
def test_read_view_frames_reads_into_a_pooled_stack(tmp_path, packed):
    truth = noise_scan(tmp_path, views=2)
    if packed:
        pack_scan(tmp_path)
    scan = load_scan(tmp_path)
    pool = FrameBuffers()
    first = read_view_frames(scan, scan.views[0], threads=1, buffers=pool)
    names = list(scan.views[0].frames)
    expect = [np.stack([truth[(k, n)] for n in names]) for k in (0, 1)]
    assert np.array_equal(first, expect[0])
    pool.give(first)
    second = read_view_frames(scan, scan.views[1], threads=1, buffers=pool)
    assert second is first and np.array_equal(second, expect[1])  # the same memory, the next view's frames
