"""kernels.launch: row runs cover every pixel once; scan_counts gives offsets and totals."""

import numpy as np
import pytest
import warp as wp

from ringscan.kernels import init_warp
from ringscan.kernels.launch import launch_rows, row_run, scan_counts

init_warp()


@wp.kernel
def _hits_kernel(row0: int, chunk: int, hits: wp.array2d(dtype=wp.int32)):
    run = row_run(wp.tid(), hits.shape[1], row0, chunk)
    for x in range(run[1], run[2]):
        wp.atomic_add(hits, run[0], x, 1)


@pytest.mark.parametrize("threads", [1, 3])
@pytest.mark.parametrize("shape", [(7, 13), (1, 1), (16, 5)])
def test_row_runs_cover_every_pixel_once(device, shape, threads):
    h, w = shape
    hits = wp.zeros(shape, dtype=wp.int32, device=device)
    launch_rows(_hits_kernel, h, w, lambda r0, chunk: [r0, chunk], [hits], device, threads)
    assert np.all(hits.numpy() == 1)


def test_scan_counts_offsets_and_total(device):
    counts = np.array([0, 3, 1, 0, 2], np.int32)
    offsets, total = scan_counts(wp.array(counts, device=device))
    assert offsets.numpy().tolist() == [0, 0, 3, 4, 4] and total == 6


def test_scan_counts_of_an_image(device):
    counts = np.arange(12, dtype=np.int32).reshape(3, 4) % 3
    offsets, total = scan_counts(wp.array(counts, device=device))
    assert total == counts.sum()
    assert offsets.numpy().ravel().tolist() == np.concatenate([[0], np.cumsum(counts.ravel())[:-1]]).tolist()


def test_scan_counts_empty(device):
    offsets, total = scan_counts(wp.zeros(0, dtype=wp.int32, device=device))
    assert total == 0 and offsets.shape == (0,)


def test_cpu_thread_budget():
    import os

    from ringscan.kernels.launch import cpu_threads, default_threads, set_cpu_threads

    try:
        set_cpu_threads(1)
        assert cpu_threads() == 1 and default_threads() == 1
        set_cpu_threads(None)
        assert cpu_threads() == (os.cpu_count() or 1)
        for bad in (0, -2, 1.5, True, "2"):
            with pytest.raises(ValueError, match="set_cpu_threads"):
                set_cpu_threads(bad)
    finally:
        set_cpu_threads(None)
