"""OpenCV's column/row Gray code on the virtual rig: the patterns, the files, and the round trip
through ``ringscan import`` against the truth projector coordinates."""

import cv2
import numpy as np
import pytest

from ringscan.pipeline.formats.images import read_image
from ringscan.pipeline.formats.patterns import DECODED_SCALE, gray_decode
from ringscan.pipeline.formats.rig import save_rig
from ringscan.pipeline.simulate.opencv_graycode import (
    graycode_bit_counts,
    graycode_frame_names,
    graycode_patterns,
    read_graycode_truth,
    render_graycode_captures,
)
from ringscan.pipeline.simulate.virtual_rig import RenderSettings
from ringscan.tools.cli import main
from tests.support.opencv_graycode_rig import PH, PW, small_procam_rig, small_stereo_rig
from tests.support.shared_data import need_shared


def bits_msb_first(frames, n_bits, first, index):
    """The Gray code read from pattern/inverse pairs (pattern > inverse), MSB first."""
    g = np.zeros_like(index)
    for k in range(n_bits):
        g = (g << 1) | (frames[first + 2 * k] > frames[first + 2 * k + 1]).astype(np.int64)
    return gray_decode(g, n_bits)


@pytest.mark.parametrize("size", [(PW, PH), (100, 60), (1280, 800)])
def test_patterns_follow_opencv_layout(size):
    w, h = size
    cb, rb = graycode_bit_counts(size)
    assert (cb, rb) == (int(np.ceil(np.log2(w))), int(np.ceil(np.log2(h))))
    pats = graycode_patterns(size)
    names = graycode_frame_names(size)
    assert len(pats) == len(names) == 2 * (cb + rb) + 2
    assert names[0] == "graycode_00" and names[-1] == f"graycode_{len(names) - 1:02d}"
    for p in pats:
        assert p.shape == (h, w) and p.dtype == np.uint8 and set(np.unique(p)) <= {0, 255}
    for k in range(0, 2 * (cb + rb), 2):                      # each pattern followed by its inverse
        assert np.array_equal(pats[k].astype(int) + pats[k + 1], np.full((h, w), 255))
    assert (pats[-2] == 255).all() and (pats[-1] == 0).all()  # white, then black
    cols = np.arange(w)[None, :].repeat(h, 0)
    rows = np.arange(h)[:, None].repeat(w, 1)
    assert np.array_equal(bits_msb_first(pats, cb, 0, cols), cols)           # columns first, constant down
    assert np.array_equal(bits_msb_first(pats, rb, 2 * cb, rows), rows)      # then rows, constant across


def test_patterns_equal_opencv_files(shared_data):
    """OpenCV's own GrayCodePattern output for a 1024x768 projector (../shared/data/procam)."""
    folder = need_shared(shared_data / "procam" / "graycode_pattern", "OpenCV's pattern files")
    pats = graycode_patterns((1024, 768))
    assert len(pats) == len(list(folder.glob("pattern_*.png"))) == 42
    for i, p in enumerate(pats):
        assert np.array_equal(cv2.imread(str(folder / f"pattern_{i:02d}.png"), cv2.IMREAD_GRAYSCALE), p), i


def test_rendered_frames_are_pairs_and_white_black(tmp_path):
    """Linear camera and light, no noise: pattern + inverse = white + black at every pixel (to rounding)."""
    rig = small_procam_rig()
    st = RenderSettings(noise=0.0, bit_depth=16)
    render_graycode_captures(tmp_path / "r", rig=rig, scene="sphere", size_mm=40.0, settings=st, progress=False,
                             device="cpu")
    files = sorted(p.name for p in (tmp_path / "r" / "capture_0").iterdir())
    assert files == [f"{n}.png" for n in graycode_frame_names((PW, PH))]
    fr = np.stack([read_image(tmp_path / "r" / "capture_0" / f).astype(np.float64) for f in files])
    white, black = fr[-2], fr[-1]
    lit = read_graycode_truth(tmp_path / "r")["lit"]
    assert (white[lit] > black[lit]).all()                   # white is the bright one, black the dark one
    assert np.median(white[lit] - black[lit]) > 10000
    pair_sum = fr[0:-2:2] + fr[1:-2:2]
    assert np.abs(pair_sum - (white + black)).max() <= 2.0


def test_round_trip_through_import(tmp_path, capsys):
    """``ringscan simulate --captures opencv-graycode`` then ``ringscan import`` with the same rig:
    the decoded projector coordinates of the pixels inside the object and the plane
    (away from silhouettes and shadow edges) match the truth projection of the
    surface point.

    Tolerance: the integer codes are the projector pixel the pixel centre sees, so
    within 0.5 px of the truth, plus the projector blur (0.7 px) and the pixel's own
    footprint (0.5 camera px ~ 0.3 projector px) near a boundary: 1 px bounds them.
    The sub-pixel positions interpolate boundaries found to a few hundredths of a
    camera pixel (noise 1.5 levels against a contrast of ~150) and are quantised to
    1/32 px: their median error must be under 0.1 px and their 95th percentile under
    0.3 px, 5x better than the integer codes' bound.
    """
    rig = small_procam_rig(gamma=2.2)
    rig_file = tmp_path / "rig.json"
    save_rig(rig_file, rig)
    out, scan = tmp_path / "render", tmp_path / "scan"
    assert main(["simulate", "--rig", str(rig_file), "--scene", "sphere", "--size-mm", "50",
                 "--captures", "opencv-graycode", "--no-progress", "--device", "cpu", "--out", str(out)]) == 0
    assert main(["import", str(out / "capture_0"), "--rig", str(out / "rig.json"), "--projector", f"{PW}x{PH}",
                 "--out", str(scan)]) == 0
    capsys.readouterr()
    truth = read_graycode_truth(out)
    assert truth["doc"]["layout"] == "opencv-graycode" and truth["doc"]["projector"] == [PW, PH]
    fu = read_image(scan / "capture_0" / "proj_u.png").astype(np.float64)
    fv = read_image(scan / "capture_0" / "proj_v.png").astype(np.float64)
    ok = (fu > 0) & (fv > 0)
    u, v = fu / DECODED_SCALE - 1.0, fv / DECODED_SCALE - 1.0
    kernel = np.ones((5, 5), np.uint8)
    inner = {}
    for name, m in (("object", truth["lit"] & truth["object"]), ("plane", truth["lit"] & ~truth["object"])):
        inner[name] = cv2.erode(m.astype(np.uint8), kernel).astype(bool)
        assert inner[name].sum() > 1000, name
        sel = inner[name]
        assert ok[sel].mean() > 0.99, name                   # every inner lit pixel decoded
        e = np.hypot(u[sel & ok] - truth["proj"][..., 0][sel & ok], v[sel & ok] - truth["proj"][..., 1][sel & ok])
        assert np.percentile(e, 99.5) < 1.0, name
        assert np.median(e) < 0.1, (name, np.median(e))
        assert np.percentile(e, 95) < 0.3, (name, np.percentile(e, 95))
    # unlit and empty pixels: never decoded
    dark = ~np.isfinite(truth["depth"]) | ~cv2.dilate(truth["lit"].astype(np.uint8), kernel).astype(bool)
    assert not ok[dark].any()


def test_wrong_projector_size_is_one_clear_error(tmp_path, capsys):
    rig = small_procam_rig()
    with pytest.raises(ValueError, match=f"projector 64x48 does not match the rig's {PW}x{PH} projector"):
        render_graycode_captures(tmp_path / "r", rig=rig, projector=(64, 48), progress=False, device="cpu")
    assert not (tmp_path / "r").exists()                     # nothing written
    with pytest.raises(ValueError, match="projector: expected"):
        render_graycode_captures(tmp_path / "r", rig=rig, projector=(1, 48), progress=False, device="cpu")
    # a capture imported with the wrong --projector: one line naming the folder and the frame count
    render_graycode_captures(tmp_path / "r", rig=rig, scene="sphere", size_mm=40.0, progress=False, device="cpu",
                             settings=RenderSettings(supersample=1))
    capsys.readouterr()
    # the folder does not hold what --projector says: the run's input (exit 1)
    assert main(["import", str(tmp_path / "r" / "capture_0"), "--rig", str(tmp_path / "r" / "rig.json"),
                 "--projector", "256x96", "--out", str(tmp_path / "scan")]) == 1
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "capture_0" in err and "30 graycode_NN frames" in err, err
    assert not (tmp_path / "scan").exists()


def test_two_cameras_in_opencv_sample_layout(tmp_path):
    """A two-camera rig renders OpenCV's sample layout: pattern_camN_imK frames from 1 (white, black last), the
    image list, the stereo and procam files (what the rig says), and each camera's truth: camera 2's truth
    projector coordinates, through camera 2's own projection, land on the pixels that see them."""
    from ringscan.pipeline.calibrate.capture_files import list_capture
    from ringscan.pipeline.calibrate.opencv_files import read_opencv_calibration, read_stereo_calibration
    from ringscan.pipeline.geometry import camera_pixels

    rig = small_stereo_rig()
    out = tmp_path / "r"
    doc = render_graycode_captures(out, rig=rig, scene="sphere", size_mm=50.0, progress=False, device="cpu",
                                   settings=RenderSettings(supersample=2))
    n = len(graycode_patterns((PW, PH)))
    names = sorted(p.name for p in (out / "capture_0").iterdir())
    assert names == sorted(f"pattern_cam{c}_im{k}.png" for c in (1, 2) for k in range(1, n + 1))
    assert not (out / "capture_0" / "pattern_cam1_im0.png").exists()
    a = list_capture(out / "capture_0", projector=(PW, PH))
    b = list_capture(out / "capture_0.yml", projector=(PW, PH))
    assert a.kind == "pattern" and b.kind == "list" and len(a.cameras) == 2
    assert [[p.resolve() for p in c] for c in a.cameras] == [[p.resolve() for p in c] for c in b.cameras]
    assert a.cameras[1][n - 2].name == f"pattern_cam2_im{n - 1}.png"        # white, then black, last
    for cam in range(2):
        truth = read_graycode_truth(out, camera=cam + 1)
        white = read_image(a.cameras[cam][n - 2]).astype(float)
        black = read_image(a.cameras[cam][n - 1]).astype(float)
        assert truth["lit"].sum() > 5000 and np.median((white - black)[truth["lit"]]) > 60
    st = read_stereo_calibration(out / "calibrationParameters.yml")
    R = rig.camera2.R @ rig.camera.R.T
    assert np.allclose(st["R"], R) and np.allclose(st["T"], rig.camera2.t - R @ rig.camera.t)
    assert st["cam1_size"] == (320, 256) and st["cam2_size"] == (320, 256)
    assert np.allclose(st["cam2_K"], rig.camera2.K) and np.allclose(st["cam2_dist"], rig.camera2.dist)
    pc = read_opencv_calibration(out / "procam.yml")
    Rp = rig.light.R @ rig.camera.R.T
    assert np.allclose(pc["R"], Rp) and np.allclose(pc["T"], rig.light.t - Rp @ rig.camera.t)
    assert pc["cam_size"] == (320, 256) and np.allclose(pc["proj_K"], rig.light.K)
    assert np.allclose(np.array(doc["camera1_from_world"])[:3, :3], rig.camera.R)
    # camera 2's truth depth: the points at those depths along camera 2's rays project back onto its pixels
    t2 = read_graycode_truth(out, camera=2)
    ys, xs = np.nonzero(np.isfinite(t2["depth"]))
    sel = slice(None, None, 97)
    from ringscan.pipeline.geometry import undistort_normalized

    xn, yn = undistort_normalized(rig.camera2, xs[sel].astype(float), ys[sel].astype(float))
    z = t2["depth"][ys[sel], xs[sel]].astype(float)
    Xc = np.stack([xn * z, yn * z, z], 1)
    Xw = (Xc - rig.camera2.t) @ rig.camera2.R
    # ... and camera 1 sees the same surface: its truth depth there agrees (where camera 1 sees the point)
    uv1 = camera_pixels(rig, Xw)
    ok = (uv1[:, 0] > 1) & (uv1[:, 0] < 318) & (uv1[:, 1] > 1) & (uv1[:, 1] < 254)
    d1 = read_graycode_truth(out, camera=1)["depth"]
    z1 = (Xw @ rig.camera.R.T + rig.camera.t)[:, 2]
    near = d1[np.round(uv1[ok, 1]).astype(int), np.round(uv1[ok, 0]).astype(int)]
    agree = np.abs(near - z1[ok]) < 1.0
    assert ok.sum() > 50 and agree.mean() > 0.8, (ok.sum(), agree.mean())   # the rest: occluded from camera 1
