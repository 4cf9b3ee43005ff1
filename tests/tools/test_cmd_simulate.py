"""``ringscan patterns`` and ``ringscan simulate`` from the command line."""

import dataclasses

import numpy as np

from ringscan.pipeline.codecs.render import render_frame
from ringscan.pipeline.formats.atomic import read_json
from ringscan.pipeline.formats.images import read_image
from ringscan.pipeline.formats.patterns import frame_names, parse_patterns
from ringscan.pipeline.formats.rig import Camera, ParallelLight, default_rig, save_rig
from ringscan.pipeline.formats.scan import load_scan
from ringscan.pipeline.simulate.truth import load_truth
from ringscan.tools.cli import main


def _small_rig_file(path):
    rig = default_rig()
    c = rig.camera
    K = np.array([[325.0, 0, 79.5], [0, 325.0, 63.5], [0, 0, 1.0]])
    rig = dataclasses.replace(
        rig, camera=Camera(width=160, height=128, K=K, dist=c.dist, R=c.R, t=c.t, gamma=2.2),
        light=ParallelLight(R=np.eye(3), t=np.zeros(3), pixel_pitch_mm=0.6, axis_px=np.array([127.5, 95.5]),
                            width=256, height=192))
    save_rig(path, rig)
    return path


def test_patterns_writes_every_frame(tmp_path):
    out = tmp_path / "p"
    assert main(["patterns", "--codec", "phase-rings", "--bits", "3", "--pitch", "5", "--sector-bits", "2",
                 "--width", "200", "--height", "150", "--out", str(out)]) == 0
    spec = parse_patterns(read_json(out / "patterns.json"))
    assert (spec.width, spec.height, spec.center, spec.steps) == (200, 150, (99.5, 74.5), 8)  # the default steps
    names = frame_names(spec)
    assert (out / "frames.txt").read_text().split() == [f"{n}.png" for n in names]
    for n in names:
        assert np.array_equal(read_image(out / f"{n}.png"), render_frame(spec, n))


def test_patterns_rings_default_pitch(tmp_path):
    assert main(["patterns", "--codec", "rings", "--out", str(tmp_path)]) == 0
    spec = parse_patterns(read_json(tmp_path / "patterns.json"))
    assert (spec.count, spec.pitch, spec.line_width) == (9, 40.0, 3.0)


def test_simulate_cli(tmp_path, capsys):
    rig = _small_rig_file(tmp_path / "rig.json")
    out = tmp_path / "scan"
    rc = main(["simulate", "--scene", "cube", "--size-mm", "40", "--rig", str(rig), "--bits", "3", "--rho0", "4",
               "--pitch", "3", "--sector-bits", "0", "--views", "2", "--supersample", "1", "--bit-depth", "16",
               "--gamma", "1.0", "--noise", "0", "--out", str(out), "--device", "cpu", "--no-progress"])
    assert rc == 0 and "2 view(s)" in capsys.readouterr().out
    scan = load_scan(out)
    assert scan.rig.camera.gamma == 1.0 and scan.patterns.center == (127.5, 95.5)
    assert [v.turntable_deg for v in scan.views] == [0.0, 180.0]
    assert read_image(scan.frame_path(scan.views[1], "white")).dtype == np.uint16
    t = load_truth(scan)
    assert t.settings["bit_depth"] == 16 and t.settings["noise"] == 0.0 and t.faces.shape == (12, 3)


def test_simulate_cli_errors(tmp_path, capsys):
    rig = _small_rig_file(tmp_path / "rig.json")
    assert main(["simulate", "--scene", "blob", "--rig", str(rig), "--out", str(tmp_path / "o")]) == 1
    assert "'blob'" in capsys.readouterr().err
    assert main(["simulate", "--rig", str(rig), "--light", "perspective", "--out", str(tmp_path / "o")]) == 2
    assert "--light" in capsys.readouterr().err
    assert main(["simulate", "--rig", str(rig), "--supersample", "0", "--out", str(tmp_path / "o")]) == 1
    assert "supersample" in capsys.readouterr().err
    assert main(["simulate", "--rig", str(tmp_path / "none.json"), "--out", str(tmp_path / "o")]) == 1
    assert "none.json" in capsys.readouterr().err


def test_simulate_cli_place_and_wall(tmp_path, capsys):
    """--place moves the object's centre, --wall adds the wall to the truth mesh; both recorded."""
    rig = _small_rig_file(tmp_path / "rig.json")
    out = tmp_path / "scan"
    assert main(["simulate", "--scene", "cube", "--size-mm", "30", "--rig", str(rig), "--bits", "3", "--rho0", "4",
                 "--pitch", "3", "--sector-bits", "0", "--supersample", "1", "--place=-10,5,40", "--wall", "10",
                 "--center", "120", "90.5",
                 "--out", str(out), "--device", "cpu", "--no-progress"]) == 0
    capsys.readouterr()
    t = load_truth(out)
    cube = t.vertices[:-4]
    assert np.allclose(0.5 * (cube.min(0) + cube.max(0)), [-10.0, 5.0, 40.0])
    assert np.all(t.vertices[-4:, 2] == 10.0) and t.faces.shape == (14, 3)
    extra = read_json(out / "scan.json")["truth"]
    assert extra["wall_z"] == 10.0 and extra["pose"]["place"] == [-10.0, 5.0, 40.0]
    assert load_scan(out).patterns.center == (120.0, 90.5)


def test_simulate_cli_opencv_graycode_errors(tmp_path, capsys):
    """Bad input for --captures opencv-graycode / --place / --wall: one line, nothing written."""
    rig = _small_rig_file(tmp_path / "rig.json")
    base = ["simulate", "--scene", "cube", "--size-mm", "30", "--rig", str(rig), "--device", "cpu", "--no-progress"]
    # options that do not go together: a usage error (2); a scene that, as placed, reaches behind the wall: the
    # scene's own size decides, the run's input (1)
    cases = [(["--captures", "opencv-graycode", "--views", "2"], "--views 2", 2),
             (["--captures", "opencv-graycode", "--image-format", "tiff"], "PNG", 2),
             (["--place", "1,2"], "--place: expected X,Y,Z", 2),
             (["--place=0,0,20", "--wall", "10"], "behind the wall", 1)]
    for k, (args, msg, code) in enumerate(cases):
        out = tmp_path / f"o{k}"
        assert main(base + args + ["--out", str(out)]) == code, args
        err = capsys.readouterr().err.strip()
        assert msg in err and len(err.splitlines()) == 1, err
        assert not out.exists() or not any(out.iterdir()), args


def test_simulate_cli_camera2(tmp_path, capsys):
    """--camera2 renders a second camera, camera 1 turned 180 degrees about the light axis: what it sees of an
    object at (x, y, z) is what camera 1 sees of the object at (-x, -y, z) (depth for depth), its frames are
    listed under the view's camera2 and its truth under truth.views.<view>.camera2."""
    rig = _small_rig_file(tmp_path / "rig.json")
    common = ["--rig", str(rig), "--scene", "sphere", "--size-mm", "30", "--codec", "gray-rings", "--bits", "3",
              "--sector-bits", "0", "--angle-steps", "0", "--supersample", "1", "--no-progress", "--device", "cpu"]
    assert main(["simulate", *common, "--camera2", "--place=12,7,20", "--out", str(tmp_path / "a")]) == 0
    assert "x 2 cameras" in capsys.readouterr().out
    assert main(["simulate", *common, "--place=-12,-7,20", "--out", str(tmp_path / "b")]) == 0
    capsys.readouterr()
    a = load_scan(tmp_path / "a")
    assert a.rig.camera2 is not None and np.allclose(a.rig.camera2.center, a.rig.camera.center * [-1, -1, 1])
    v = a.views[0]
    assert v.camera2 is not None and set(v.camera2.frames) == set(v.frames) == set(frame_names(a.patterns))
    assert all(p.startswith("view_000/cam2/") and (a.folder / p).is_file() for p in v.camera2.frames.values())
    ta, tb = load_truth(a), load_truth(tmp_path / "b")
    d2, d1 = ta.depth("view_000", camera=2), tb.depth("view_000")
    obj = np.isfinite(d1) & (d1 < np.nanmedian(d1) - 5)     # the sphere, in front of the plane
    assert obj.sum() > 200
    assert np.array_equal(np.isfinite(d2), np.isfinite(d1))
    assert np.median(np.abs(d2 - d1)[obj]) < 0.05 and np.percentile(np.abs(d2 - d1)[obj], 99) < 1.0
    assert not np.allclose(ta.depth("view_000", camera=1)[obj], d1[obj], atol=1.0)  # camera 1 sees it elsewhere
    assert ta.lit("view_000", camera=2).shape == (128, 160)


def _relative_files(folder):
    return sorted(str(p.relative_to(folder)) for p in folder.rglob("*") if p.is_file())


def test_simulate_cli_mitsuba_writes_the_scan_and_truth_of_warp(tmp_path, capsys):
    """--renderer mitsuba writes the same files as ringscan's own renderer (parallel light: Mitsuba's
    distant projector), and the two independent ray casts agree on the truth: the cube's and the
    plane's depth to float32 rounding, the lit mask but for pixels on a shadow's or the image's edge."""
    rig = _small_rig_file(tmp_path / "rig.json")
    base = ["simulate", "--scene", "cube", "--size-mm", "40", "--rig", str(rig), "--bits", "2", "--rho0", "4",
            "--pitch", "3", "--sector-bits", "0", "--angle-steps", "0", "--supersample", "1", "--no-progress"]
    assert main(base + ["--out", str(tmp_path / "warp"), "--device", "cpu"]) == 0
    assert main(base + ["--out", str(tmp_path / "mi"), "--renderer", "mitsuba"]) == 0
    assert "(Mitsuba " in capsys.readouterr().out
    assert _relative_files(tmp_path / "mi") == _relative_files(tmp_path / "warp")
    doc = read_json(tmp_path / "mi" / "scan.json")["truth"]
    assert doc["renderer"]["name"] == "mitsuba" and doc["renderer"]["spp"] == 4
    assert doc["renderer"]["variant"] in ("llvm_ad_rgb", "scalar_rgb") and doc["renderer"]["parallel_distance_mm"] == 1e8
    assert doc["renderer"]["max_depth"] == 3 and "renderer" not in read_json(tmp_path / "warp" / "scan.json")["truth"]
    tw, tm = load_truth(tmp_path / "warp"), load_truth(tmp_path / "mi")
    dw, dm = tw.depth("view_000"), tm.depth("view_000")
    assert np.array_equal(np.isfinite(dw), np.isfinite(dm)) and np.isfinite(dw).all()
    # both intersect in float32 at ~450 mm (ulp 3e-5 mm): a few ulps apart (measured 1.2e-4 mm)
    assert np.nanmax(np.abs(dw - dm)) < 5e-4
    lw, lm = tw.lit("view_000"), tm.lit("view_000")
    assert lw.sum() > 5000 and (lw != lm).sum() <= 0.001 * lw.sum()   # measured: none differ


def test_simulate_cli_mitsuba_errors(tmp_path, capsys, monkeypatch):
    """OpenCV captures with Mitsuba, Mitsuba not installed: one
    line each, nothing written."""
    rig = _small_rig_file(tmp_path / "rig.json")
    base = ["simulate", "--scene", "cube", "--size-mm", "30", "--rig", str(rig), "--no-progress"]
    cases = [(["--renderer", "mitsuba", "--captures", "opencv-graycode"], "scan folders only", 2)]
    for k, (args, msg, code) in enumerate(cases):
        out = tmp_path / f"o{k}"
        assert main(base + args + ["--out", str(out)]) == code, args
        err = capsys.readouterr().err.strip()
        assert msg in err and len(err.splitlines()) == 1, err
        assert not out.exists() or not any(out.iterdir()), args
    import ringscan.pipeline.simulate.mitsuba_render as mr

    monkeypatch.setattr(mr, "mitsuba_available", lambda: False)
    out = tmp_path / "missing"
    assert main(base + ["--renderer", "mitsuba", "--out", str(out)]) == 1
    err = capsys.readouterr().err.strip()
    assert "pip install 'ringscan[mitsuba]'" in err and len(err.splitlines()) == 1, err
    assert not out.exists() or not any(out.iterdir())
