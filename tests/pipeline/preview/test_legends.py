"""The pictures' scales read right (issue 35, item 5): one colour and a legend entry a category (a
view), round ticks in one format and a unit that makes them readable (um, not 0.00409 mm), the
confidence on its own 0..1 range, the length unit the data is in ("board units" for a scan whose
calibration stated none), a message on a map panel that is empty and why, and pixels without a
point marked, not white. Each read back from what was drawn (the labels, the figure's texts and
legend), not from pixels."""

from __future__ import annotations

import json
import math

import numpy as np
import open3d as o3d
import pytest

from ringscan.pipeline.evaluate.conditioning import ConditioningMap, conditioning_figure
from ringscan.pipeline.evaluate.residuals import NO_POINT_LABEL, ResidualMap, residual_map_figure
from ringscan.pipeline.formats.meshes import write_mesh
from ringscan.pipeline.formats.ply import write_ply
from ringscan.pipeline.preview.clouds import BOARD_UNITS, length_unit
from ringscan.pipeline.preview.colour import nice_ticks, readable_unit
from ringscan.tools import cmd_view
from ringscan.tools.cli import main


@pytest.mark.parametrize("lo, hi", [(0.0, 0.00409), (0.0, 4.09), (0.0, 1.0), (0.2, 0.97), (-0.0123, 0.0123),
                                    (1.0, 6.0), (0.0, 27.3), (1e-4, 3e3)])
def test_ticks_are_round_in_one_format_and_inside_the_range(lo, hi):
    ticks, labels = nice_ticks(lo, hi)
    assert 3 <= len(ticks) <= 7 and lo - 1e-12 <= ticks[0] and ticks[-1] <= hi + 1e-12
    step = ticks[1] - ticks[0]
    assert np.allclose(np.diff(ticks), step)
    mant = step / 10.0 ** math.floor(math.log10(step))
    assert min(abs(mant - m) for m in (1, 2, 2.5, 5, 10)) < 1e-6, step  # a round step
    assert np.allclose(ticks / step, np.rint(ticks / step))  # on multiples of it
    decimals = {len(s.split(".")[1]) if "." in s else 0 for s in labels}
    assert len(decimals) == 1, labels  # one number format
    assert np.allclose([float(s) for s in labels], ticks, atol=step * 1e-6)  # the label is the value


def test_a_small_length_reads_in_um():
    assert readable_unit(0.00409, "mm") == ("um", 1000.0)
    assert readable_unit(0.5, "mm") == ("mm", 1.0) and readable_unit(0.004, "px") == ("px", 1.0)
    assert nice_ticks(0.0, 4.09)[1] == ["0", "1", "2", "3", "4"]  # 0.00409 mm as um


class _Spy:
    """ringscan view's render_to_png, recording what it drew."""

    def __init__(self, monkeypatch):
        self.calls, real = [], cmd_view.render_to_png

        def spy(*a, **k):
            res = real(*a, **k)
            self.calls.append((k, res))
            self.geoms = a[0]
            return res

        monkeypatch.setattr(cmd_view, "render_to_png", spy)


def _cloud_ply(path, n=3000, views=3, seed=0):
    rng = np.random.default_rng(seed)
    p = rng.normal(size=(n, 3))
    p = 15.0 * p / np.linalg.norm(p, axis=1, keepdims=True) + [0, 0, 20]
    write_ply(path, {"x": p[:, 0], "y": p[:, 1], "z": p[:, 2],
                     "view": (np.arange(n) % views).astype(np.int32),
                     "confidence": rng.uniform(0.3, 0.6, n).astype(np.float32)})
    return p


def test_views_get_one_colour_each_and_a_legend(tmp_path, monkeypatch):
    _cloud_ply(tmp_path / "fused.ply")
    spy = _Spy(monkeypatch)
    assert main(["view", str(tmp_path / "fused.ply"), "--out", str(tmp_path / "v.png"), "--color-by", "view",
                 "--width", "240", "--height", "200", "--renderer", "software", "--no-progress"]) == 0
    (kwargs, res), = spy.calls
    assert res.legend == ["view 0", "view 1", "view 2"]  # a legend, no continuous bar (ticks 1.75, 5.25 before)
    colours = np.array([c for _, c in kwargs["colorbar_spec"]["categories"]])
    assert len({tuple(c) for c in colours}) == 3
    painted = np.asarray(spy.geoms[0].colors)  # each point the colour its view has in the legend
    assert np.allclose(painted, colours[np.arange(len(painted)) % 3])


def test_confidence_has_its_own_range_0_to_1(tmp_path, monkeypatch):
    _cloud_ply(tmp_path / "c.ply")  # confidences 0.3 .. 0.6 only
    spy = _Spy(monkeypatch)
    assert main(["view", str(tmp_path / "c.ply"), "--out", str(tmp_path / "c.png"), "--color-by", "confidence",
                 "--width", "240", "--height", "200", "--renderer", "software", "--no-progress"]) == 0
    (kwargs, res), = spy.calls
    assert (kwargs["colorbar_spec"]["vmin"], kwargs["colorbar_spec"]["vmax"]) == (0.0, 1.0)
    assert res.legend == ["0.00", "0.25", "0.50", "0.75", "1.00"]


def test_an_error_of_microns_reads_in_um_with_round_ticks(tmp_path, monkeypatch, capsys):
    mesh = o3d.geometry.TriangleMesh.create_sphere(15.0, resolution=80)
    write_mesh(tmp_path / "truth.ply", mesh)
    rng = np.random.default_rng(1)
    p = rng.normal(size=(4000, 3))
    p = (15.0 + rng.normal(0, 0.002, (4000, 1))) * p / np.linalg.norm(p, axis=1, keepdims=True)  # ~2 um off
    write_ply(tmp_path / "c.ply", {"x": p[:, 0], "y": p[:, 1], "z": p[:, 2]})
    spy = _Spy(monkeypatch)
    assert main(["view", str(tmp_path / "c.ply"), "--truth", str(tmp_path / "truth.ply"), "--out",
                 str(tmp_path / "e.png"), "--width", "240", "--height", "200", "--renderer", "software",
                 "--no-progress"]) == 0
    (kwargs, res), = spy.calls
    assert kwargs["colorbar_spec"]["label"] == "dist (um)"
    ticks = [float(s) for s in res.legend]
    # the tessellated sphere's facets add up to ~20 um; the ticks are whole microns or round steps of them
    assert ticks[0] == 0.0 and all(t == round(t, 1) for t in ticks) and len(ticks) >= 3, res.legend


def test_a_scan_in_board_units_says_so(tmp_path, monkeypatch, capsys):
    """A view's PLY of a scan imported from a calibration that stated no units: the scale bar and the
    height bar say "board units", not mm."""
    scan, recon = tmp_path / "scan", tmp_path / "recon"
    scan.mkdir()
    recon.mkdir()
    (scan / "scan.json").write_text(json.dumps({"imported": {"units": {"mm_per_unit": 1.0, "source": "assumed"}}}))
    (recon / "report.json").write_text(json.dumps({"scan": str(scan), "views": []}))
    _cloud_ply(recon / "view_000.ply")
    assert length_unit(recon / "view_000.ply") == BOARD_UNITS
    spy = _Spy(monkeypatch)
    assert main(["view", str(recon / "view_000.ply"), "--out", str(tmp_path / "h.png"), "--color-by", "height",
                 "--width", "240", "--height", "200", "--renderer", "software", "--no-progress"]) == 0
    (kwargs, res), = spy.calls
    assert res.scale_bar_label.endswith(" board units") and kwargs["colorbar_spec"]["label"] == "z (board units)"
    assert "board units" in capsys.readouterr().out
    (scan / "scan.json").write_text(json.dumps({"imported": {"units": {"mm_per_unit": 1.0, "source": "given"}}}))
    assert length_unit(recon / "view_000.ply") == "mm"


def _texts(fig) -> str:
    return " ".join(t.get_text() for ax in fig.axes for t in [*ax.texts, ax.title]).replace("\n", " ")


def test_an_empty_conditioning_panel_says_why():
    """The map of an imported (decoded) scan: no camera pixel sees a ring, three empty panels; each says
    so, and why (the caller's reason first), instead of "0 % of lit pixels"."""
    empty = np.full((12, 16), np.nan, np.float32)
    cmap = ConditioningMap(sigma={"rings": empty, "angle": empty, "both": empty}, lit=np.zeros((12, 16), bool),
                           step=8, plane_z=20.0)
    fig = conditioning_figure(cmap, empty_why="scan was decoded on import (codec 'decoded')")
    text = _texts(fig)
    assert text.count("no camera pixel sees the coded rings on the plane z = 20 mm") == 3
    assert text.count("codec 'decoded'") == 3 and "0 % of lit pixels" not in text
    legend = [t.get_text() for ax in fig.axes if ax.get_legend() for t in ax.get_legend().get_texts()]
    assert legend == ["not lit by the rings", "lit, dropped by the constraint"]
    # one panel empty among full ones: only it says so
    full = np.full((12, 16), 0.01, np.float32)
    cmap = ConditioningMap(sigma={"rings": empty, "angle": full, "both": full}, lit=np.ones((12, 16), bool),
                           step=8, plane_z=20.0)
    text = _texts(conditioning_figure(cmap))
    assert "the 'rings' constraint places none of the 192 lit pixels" in text and text.count("no value") == 1
    assert "angle: 100 % of lit pixels" in text


def test_pixels_without_a_point_are_marked_not_white():
    r = np.full((20, 30), 0.05)
    r[::2, ::3] = np.nan  # a board's undecoded squares
    fig = residual_map_figure(ResidualMap(residual=r, summary={"points": int(np.isfinite(r).sum()),
                                                               "median": 0.05, "p95": 0.05}))
    (ax,) = [a for a in fig.axes if a.get_legend()]
    assert [t.get_text() for t in ax.get_legend().get_texts()] == [NO_POINT_LABEL]
    (bg,) = [p for p in ax.patches if p.get_hatch()]
    assert bg.get_facecolor()[:3] != (1.0, 1.0, 1.0)
    assert "white" not in " ".join(a.get_ylabel() for a in fig.axes)


def test_a_views_own_camera_render_marks_where_nothing_was_decoded(tmp_path):
    """Seen from its own camera, a view's holes (a board's dark squares) are hatched and keyed, not white."""
    import cv2

    from ringscan.pipeline.preview.render import HATCH_BGR, ViewSettings, render_to_png

    p = np.random.default_rng(2).uniform(-10, 10, (4000, 3)) * [1, 1, 0] + [0, 0, 0]
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(p))
    s = ViewSettings(width=200, height=160, renderer="software")
    res = render_to_png([cloud], tmp_path / "a.png", settings=s, empty_label=cmd_view.NOT_DECODED)
    assert res.empty_label == "no point (not decoded)"
    img = cv2.imread(str(tmp_path / "a.png"))
    assert (np.all(img == HATCH_BGR, axis=2)).sum() > 100  # the empty pixels carry the hatch
    plain = render_to_png([cloud], tmp_path / "b.png", settings=s)
    assert plain.empty_label is None and not np.all(cv2.imread(str(tmp_path / "b.png")) == HATCH_BGR, axis=2).any()


def test_fuse_draws_a_scale_bar_on_its_preview(tmp_path, monkeypatch, capsys):
    """`ringscan fuse` asks for preview.png's scale bar (as the demo does) and says its length."""
    from ringscan.tools import cmd_fuse

    asked = {}

    def fake(sources, out, **kw):  # the workflow itself is tested in tests/pipeline/fusion; here: what fuse asks
        asked.update(kw)
        raise KeyboardInterrupt

    monkeypatch.setattr(cmd_fuse, "fuse_and_mesh", fake)
    (tmp_path / "recon").mkdir()
    assert main(["fuse", str(tmp_path / "recon"), "--out", str(tmp_path / "out"), "--no-progress"]) == 130
    assert asked["preview_scale_bar"] is True
