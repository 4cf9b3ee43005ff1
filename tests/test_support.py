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


def test_a_cached_frame_is_a_copy_of_the_drawn_one(monkeypatch):
    """tests/support/frame_cache.py: the same bytes as drawing the frame, a fresh copy each call (a caller that
    writes into it changes nothing for the next); frames of another codec's kinds are not kept."""
    import numpy as np

    from ringscan.pipeline.codecs.render import render_frame
    from ringscan.pipeline.formats.patterns import frame_names, parse_patterns
    from tests.pipeline.reconstruct.tiny_scan import TINY_PATTERNS
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
