"""The suite's own helpers (tests/support/): printed figures read as numbers, shared data in and out of CI."""

from __future__ import annotations

import pytest

from tests.support.printed import assert_figures_as_quoted, printed_figure, printed_figures
from tests.support.shared_data import need_shared

LINE = "projector: RMS reprojection error 0.217 px over 3 views; fx 1887.1 fy 1876.6 cx 457.4 cy 857.4; ..."


def test_printed_figures_are_read_as_numbers():
    assert printed_figures(LINE, "fx {} fy {}") == (1887.1, 1876.6)
    assert printed_figure("roll -0.002 deg; T 1e-3", "roll {} deg") == -0.002
    assert printed_figure("T 1.5e-3,", "T {},") == 1.5e-3
    with pytest.raises(AssertionError, match="nothing matches 'baseline {}'"):
        printed_figure(LINE, "baseline {}")


def test_a_figure_agrees_with_its_quote_within_the_tolerance_and_its_printing():
    quoted = "fx 1887.1\nfy 1876.6"  # a quote wrapped over two lines
    # 1876.66 prints as 1876.7 where the doc says 1876.6: the same figure, within its last decimal
    assert_figures_as_quoted("fx 1887.14 fy 1876.66", quoted, "fx {} fy {}", rtol=1e-4, why="test")
    with pytest.raises(AssertionError, match="printed 1888.1, quoted 1887.1"):
        assert_figures_as_quoted("fx 1888.1 fy 1876.6", quoted, "fx {} fy {}", rtol=1e-4, why="test")


def test_missing_shared_data_fails_in_ci_and_skips_elsewhere(tmp_path, monkeypatch):
    assert need_shared(tmp_path) == tmp_path
    monkeypatch.setenv("CI", "true")
    with pytest.raises(pytest.fail.Exception, match="procam captures not found: .*nowhere"):
        need_shared(tmp_path / "nowhere", "procam captures")
    monkeypatch.delenv("CI")
    with pytest.raises(pytest.skip.Exception, match="not found"):
        need_shared(tmp_path / "nowhere")


def test_a_projector_window_around_what_the_camera_sees_gives_the_whole_projectors_frames(tmp_path):
    """tests/support/projector_window.py on the tiny rig's projector (256x192, cheap to render whole), seen by
    the tiny camera cut to its middle 32x24 pixels: the window around the projector pixels it sees renders
    the same camera frames, to the rounding of the defocus blur's float sums (one grey level here and there)."""
    import dataclasses

    import numpy as np

    from ringscan.pipeline.formats.patterns import parse_patterns
    from ringscan.pipeline.formats.scan import read_view_frames
    from ringscan.pipeline.simulate.scan import simulate_scan
    from tests.support.tiny_scan import TINY_PATTERNS, tiny_rig
    from tests.support.projector_window import projector_window, seen_projector_pixels

    rig = tiny_rig()
    K = rig.camera.K.copy()
    K[:2, 2] -= [64, 52]
    rig = dataclasses.replace(rig, camera=dataclasses.replace(rig.camera, width=32, height=24, K=K))
    spec = {**TINY_PATTERNS, "bits": 2, "sector_bits": 3}  # 12 frames: rings and sectors, their edges blurred

    def render(name, r, s):
        scan = simulate_scan(tmp_path / name, scene="sphere", size_mm=40.0, rig=r, patterns=parse_patterns(s),
                             progress=False)
        return scan, read_view_frames(scan, scan.views[0]).astype(np.int16)

    whole, a = render("whole", rig, spec)
    p = seen_projector_pixels(whole)
    lo = [int(x) for x in np.floor(np.minimum(p.min(0), spec["center"]) - 4)]  # 4 px: the blur (sigma 0.7 px) and more
    hi = [int(x) for x in np.ceil(np.maximum(p.max(0), spec["center"]) + 4)]
    assert min(lo) > 0 and hi[0] < 255 and hi[1] < 191, (lo, hi)  # a window, not the whole projector
    cut_rig, cut_spec = projector_window(rig, spec, lo[0], lo[1], hi[0] - lo[0], hi[1] - lo[1])
    assert cut_rig.light.width * cut_rig.light.height < 0.5 * 256 * 192
    cut, b = render("cut", cut_rig, cut_spec)
    assert a.shape == b.shape == (12, 24, 32)
    d = np.abs(a - b)
    assert d.max() <= 1 and np.count_nonzero(d) <= 1e-3 * d.size, (d.max(), np.count_nonzero(d))
    # and the same points of the object: each seen pixel's projector pixel moved by the window's corner
    np.testing.assert_allclose(seen_projector_pixels(cut), p - lo, atol=1e-9)


def test_a_cached_frame_is_a_copy_of_the_drawn_one(monkeypatch):
    """tests/support/frame_cache.py: the same bytes as drawing the frame, a fresh copy each call (a caller that
    writes into it changes nothing for the next); frames of another codec's kinds are not kept."""
    import numpy as np

    from ringscan.pipeline.codecs.render import render_frame
    from ringscan.pipeline.formats.patterns import frame_names, parse_patterns
    from tests.support.tiny_scan import TINY_PATTERNS
    from tests.support import frame_cache

    spec = parse_patterns(TINY_PATTERNS)
    for name in frame_names(spec):
        a = frame_cache.cached_render_frame(spec, name)
        assert np.array_equal(a, render_frame(spec, name)), name
        a[:] = 7
        assert np.array_equal(frame_cache.cached_render_frame(spec, name), render_frame(spec, name)), name
    other = parse_patterns({**TINY_PATTERNS, "pitch": 4.0})  # another pattern set: its own frames
    assert not np.array_equal(frame_cache.cached_render_frame(other, "gray_2"), render_frame(spec, "gray_2"))
    drawn = []
    monkeypatch.setattr(frame_cache, "render_frame", lambda sp, nm: drawn.append(nm) or np.zeros((2, 2), np.uint8))
    n = len(frame_cache._frames)
    for _ in range(2):
        frame_cache.cached_render_frame(spec, "proj_u")  # a kind another codec draws (render_frame's registry)
    assert drawn == ["proj_u", "proj_u"] and len(frame_cache._frames) == n  # drawn each time, not kept
