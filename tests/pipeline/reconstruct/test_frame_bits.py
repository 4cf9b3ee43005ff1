"""A 12-bit camera's scan (16-bit frames, values 0..4095): with scan.json's
``frame_bits`` it reconstructs as its full 16-bit original does; without it, the
view's no-contrast message says what to set (docs/formats.md)."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest
from scipy.spatial import cKDTree

from ringscan.pipeline.evaluate.metrics import evaluate_recon
from ringscan.pipeline.formats.atomic import read_json
from ringscan.pipeline.formats.images import read_image, write_image
from ringscan.pipeline.formats.patterns import parse_patterns
from ringscan.pipeline.formats.ply import read_ply
from ringscan.pipeline.reconstruct.scan import reconstruct_scan
from ringscan.pipeline.simulate.scan import simulate_scan
from ringscan.pipeline.simulate.virtual_rig import RenderSettings
from ringscan.tools.cli import main
from tests.support.tiny_scan import TINY_PATTERNS, tiny_rig


@pytest.fixture(scope="module")
def full(tmp_path_factory):
    """The tiny scan at 16 bits, and its reconstruction."""
    root = tmp_path_factory.mktemp("framebits")
    scan = simulate_scan(root / "full", scene="sphere", size_mm=40.0, rig=tiny_rig(),
                         patterns=parse_patterns(TINY_PATTERNS), settings=RenderSettings(bit_depth=16), progress=False)
    reconstruct_scan(scan, root / "full_rec", device="cpu", progress=False)
    return root


def _twelve_bit_copy(full, dst, frame_bits):
    """The 16-bit scan as a 12-bit camera records it (every frame shifted right by 4), in ``dst``."""
    shutil.copytree(full / "full", dst)
    for p in (dst / "view_000").glob("*.png"):
        img = read_image(p)
        write_image(p, img >> 4)
    if frame_bits is not None:
        d = json.loads((dst / "scan.json").read_text())
        d["frame_bits"] = frame_bits
        (dst / "scan.json").write_text(json.dumps(d))
    return dst


def _points(folder):
    ply = read_ply(folder / "view_000.ply")
    return np.stack([ply[k] for k in "xyz"], axis=1).astype(np.float64)


def test_a_12_bit_scan_with_frame_bits_gives_the_16_bit_scans_points(full, tmp_path):
    scan = _twelve_bit_copy(full, tmp_path / "b12", 12)
    reconstruct_scan(scan, tmp_path / "rec", device="cpu", progress=False)
    a, b = _points(full / "full_rec"), _points(tmp_path / "rec")
    assert len(a) > 100 and len(b) == len(a)
    # Bit replication leaves every grey level within 15 of 65536 of the original's (0.06 of an
    # 8-bit level, 1/25 of the simulated camera noise's 1.5 levels): an edge crossing moves by a
    # small fraction of the noise's own scatter, so every point stays within 0.02 mm of its
    # original (the points lie 0.05 mm from the truth, median) and the median far less.
    d, _ = cKDTree(a).query(b)
    assert d.max() < 0.02 and np.median(d) < 0.002
    ea = evaluate_recon(full / "full_rec", full / "full")["all"]
    eb = evaluate_recon(tmp_path / "rec", full / "full")["all"]
    assert ea["median_mm"] < 0.1 and abs(eb["median_mm"] - ea["median_mm"]) < 0.002
    assert abs(eb["p95_mm"] - ea["p95_mm"]) < 0.005


def test_without_frame_bits_the_view_fails_with_the_hint_and_setting_it_redoes_the_view(full, tmp_path, capsys):
    scan = _twelve_bit_copy(full, tmp_path / "b12", None)
    out = tmp_path / "rec"
    rc = main(["reconstruct", str(scan), "--out", str(out), "--device", "cpu", "--no-progress"])
    err = capsys.readouterr().err
    assert rc == 1
    brightest = int(read_image(scan / "view_000" / "white.png").max())
    assert brightest < 4096
    hint = (f"16-bit frames whose brightest value is {brightest}: a 10- or 12-bit camera's frames? set frame_bits "
            f"in scan.json (docs/formats.md)")
    assert "no contrast between the white and black frames" in err and hint in err
    assert hint in read_json(out / "report.json")["views"][0]["no_points"]
    # frame_bits set: the same output folder, resumed, redoes the view (frame_bits is an input)
    d = json.loads((scan / "scan.json").read_text())
    d["frame_bits"] = 12
    (scan / "scan.json").write_text(json.dumps(d))
    rc = main(["reconstruct", str(scan), "--out", str(out), "--device", "cpu", "--no-progress", "--resume"])
    assert rc == 0
    assert len(_points(out)) == len(_points(full / "full_rec"))


def test_dark_frames_of_a_scan_that_sets_frame_bits_get_no_hint(full, tmp_path, capsys):
    scan = _twelve_bit_copy(full, tmp_path / "b12", 16)  # wrongly says 16: dark, but frame_bits is set
    rc = main(["reconstruct", str(scan), "--out", str(tmp_path / "rec"), "--device", "cpu", "--no-progress"])
    err = capsys.readouterr().err
    assert rc == 1 and "no contrast between the white and black frames" in err and "frame_bits" not in err


def test_a_frame_above_the_range_stops_the_reconstruction_naming_it(full, tmp_path, capsys):
    scan = _twelve_bit_copy(full, tmp_path / "b12", 12)
    p = scan / "view_000" / "gray_0.png"
    img = read_image(p)
    img[5, 6] = 4096
    write_image(p, img)
    rc = main(["reconstruct", str(scan), "--out", str(tmp_path / "rec"), "--device", "cpu", "--no-progress"])
    err = capsys.readouterr().err
    assert rc != 0
    assert f"{p}: frame holds 4096, above the 12-bit range frame_bits says (4095)" in err
    assert len(err.strip().splitlines()) == 1 and "Traceback" not in err
