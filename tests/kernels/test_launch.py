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


# ----------------------------------------------------------------------------- CUDA's launch geometry on the CPU
# On CUDA every stage is one launch of a thread per pixel (row runs of chunk 1) or per
# item (spans from i0 = 0): code that never runs on a machine without a GPU. Run it on
# the CPU backend (launch._one_launch forced on) and compare every output, byte for
# byte, with the CPU's own slices.


@pytest.fixture
def cuda_geometry(monkeypatch):
    """Switch launch_rows/launch_spans to CUDA's geometry (one launch, chunk 1) while
    on; yields the switch (``on`` True/False) and counts the launches it made."""
    import ringscan.kernels.launch as launch

    state = {"on": False, "single": 0}

    def one_launch(dev):
        assert dev.is_cpu
        state["single"] += state["on"]
        return state["on"]

    monkeypatch.setattr(launch, "_one_launch", one_launch)
    return state


def _both(state, run):
    """run() with the CPU's slices, then with CUDA's geometry: the two results as
    dicts of NumPy arrays."""
    state["on"] = False
    a = run()
    n0 = state["single"]
    state["on"] = True
    b = run()
    state["on"] = False
    assert state["single"] > n0, "CUDA's geometry was not taken"
    return a, b


def _assert_same_bytes(a: dict, b: dict):
    assert a.keys() == b.keys()
    for k in a:
        x, y = np.asarray(a[k]), np.asarray(b[k])
        assert x.shape == y.shape and x.dtype == y.dtype and x.tobytes() == y.tobytes(), k


def _fields(obj, names):
    return {k: getattr(obj, k).numpy() for k in names if getattr(obj, k) is not None}


@pytest.mark.parametrize("dtype, width", [(np.uint8, 160), (np.uint8, 157), (np.uint16, 160)])
def test_gray_rings_decode_and_samples_in_cuda_geometry(cuda_geometry, dtype, width):
    """Decode (8-bit words at width 160, the pixel kernel at 157 or 16 bits) and the
    count / scan / write of the edge samples, with the blur correction."""
    from ringscan.kernels.ring_labels import decode_gray_rings
    from ringscan.kernels.ring_sampling import sample_gray_rings
    from ringscan.kernels.settings import SampleSettings
    from tests.support.ring_frames import frame_stack, gray_rings_spec

    spec = gray_rings_spec(width=width, height=96, center=(77.3, 47.6), bits=4, sector_bits=3, pitch=3.0, rho0=5.0)
    frames = wp.array(frame_stack(spec, blur=0.9, dtype=dtype), device="cpu")

    def run():
        lab = decode_gray_rings(frames, bits=spec.bits, sector_bits=spec.sector_bits, threads=3)
        s = sample_gray_rings(frames, lab, bits=spec.bits, settings=SampleSettings(ring_curvature=True), threads=3,
                              rho0=spec.rho0, pitch=spec.pitch)
        assert len(s) > 500
        return {**_fields(lab, ("code", "weak", "band", "sector", "contrast")),
                **{f"s_{k}": v for k, v in s.numpy().items()}}

    _assert_same_bytes(*_both(cuda_geometry, run))


def test_phase_rings_in_cuda_geometry(cuda_geometry):
    """Wrapped phase and unwrapping, the pair-wise smoothing and the compaction of the points."""
    from ringscan.kernels.phase import compact_phase_points, smooth_phase
    from tests.support.phase_frames import phase_decode, phase_spec, phase_stack

    spec = phase_spec()
    frames = phase_stack(spec, noise=1.5, cam_gamma=2.2, seed=3)

    def run():
        _, lab, ph = phase_decode(frames, spec, "cpu", cam_gamma=2.2)
        sm = smooth_phase(ph, lab.sector, rho0=spec.rho0, pitch=spec.pitch, threads=3)
        pts = compact_phase_points(sm, rho0=spec.rho0, pitch=spec.pitch, threads=3)
        assert len(pts) > 3000
        return {**_fields(ph, ("t", "modulation", "status")), **_fields(sm, ("t", "status", "sector", "flags")),
                **{f"p_{k}": v for k, v in pts.numpy().items()}}

    _assert_same_bytes(*_both(cuda_geometry, run))


def test_ring_lines_in_cuda_geometry(cuda_geometry):
    """The two smoothing passes and the count / scan / write of the line centres."""
    from ringscan.kernels.ring_lines import detect_ring_lines
    from tests.support.ring_lines_image import circles_image

    img = wp.array(circles_image(noise=1.0)[None], device="cpu")

    def run():
        lines = detect_ring_lines(img, threads=3)
        assert len(lines) > 500
        return {**lines.numpy(), "smoothed": lines.smoothed.numpy()}

    _assert_same_bytes(*_both(cuda_geometry, run))


def test_spans_in_cuda_geometry(cuda_geometry):
    """1-D stages: the angle decode, the neighbour filter (points in pixel order and not)."""
    from ringscan.kernels.point_filter import mark_isolated_points
    from ringscan.pipeline.formats.patterns import angle_zones
    from tests.support.angle_frames import BANDS, PITCH, RHO0, SB, angle_decode, angle_frames, angle_lut, angle_samples
    from tests.support.plane_points import plane_points

    zones = angle_zones(rho0=RHO0, pitch=PITCH, bands=BANDS, sector_bits=SB, min_period_px=12.0)
    frames, _, _ = angle_frames(noise=2.0, zones=zones)
    pts, rho, _, sector = angle_samples(n=20000)
    cam, X, pix = plane_points(w=160, h=120)
    X = X + np.random.default_rng(2).normal(0.0, 2.0, X.shape).astype(np.float32)
    shuffled = np.random.default_rng(3).permutation(len(X))

    def run():
        ang = angle_decode("cpu", frames, pts, rho, sector, zones, angle_lut(1.0))
        out = {f"a_{k}": v for k, v in _fields(ang, ("phi", "sigma_tan", "modulation", "status")).items()}
        for name, order in (("sorted", np.arange(len(X))), ("shuffled", shuffled)):
            out[name] = mark_isolated_points(wp.array(X[order], dtype=wp.vec3, device="cpu"),
                                             wp.array(pix[order], device="cpu"),
                                             wp.zeros(len(X), dtype=wp.int32, device="cpu"), camera=cam, width=160,
                                             height=120, isolated_status=6, threads=3).numpy()
        assert 0 < np.count_nonzero(out["sorted"] == 6) < len(X) // 2
        return out

    _assert_same_bytes(*_both(cuda_geometry, run))


def test_callers_on_threads_of_their_own_load_a_kernel_once(monkeypatch):
    """Four callers (an import's cameras, say) launch the same kernel at once, each on its own thread, the
    kernel not yet launched in this process (``_warmed`` emptied): one of them makes the first launch, which
    loads the module (not thread-safe in Warp), and the others wait for it; then all launch alike."""
    import threading

    from ringscan.kernels import launch as L
    from ringscan.kernels.compact import gather

    monkeypatch.setattr(L, "_warmed", set())
    cold, real = [], wp.launch

    def counted(*a, **k):
        if not L._warmed:
            cold.append(threading.get_ident())
        return real(*a, **k)

    monkeypatch.setattr(L.wp, "launch", counted)
    src = wp.array(np.arange(100, dtype=np.float32), device="cpu")
    index = wp.array(np.arange(0, 100, 3, dtype=np.int32), device="cpu")
    gate = threading.Barrier(4)
    out = {}

    def call(t):
        gate.wait()
        out[t] = gather(src, index, threads=1).numpy()

    threads = [threading.Thread(target=call, args=(t,)) for t in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert len(cold) == 1
    assert all(np.array_equal(out[t], np.arange(0, 100, 3, dtype=np.float32)) for t in range(4))
