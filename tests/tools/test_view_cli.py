"""``ringscan view``: the PNG it writes shows the object where the camera puts it."""

from __future__ import annotations

import cv2
import numpy as np
import open3d as o3d
import pytest

from ringscan.pipeline.formats.meshes import write_mesh
from ringscan.pipeline.preview.render import ViewSettings, offscreen_available, view_camera
from ringscan.tools.cli import main


def _ellipsoid():
    m = o3d.geometry.TriangleMesh.create_sphere(1.0, resolution=60)
    m.vertices = o3d.utility.Vector3dVector(np.asarray(m.vertices) * [20.0, 12.0, 15.0] + [10.0, 0.0, 15.0])
    m.compute_vertex_normals()
    return m


def _expected(points, settings) -> np.ndarray:
    K, E = view_camera((points.min(axis=0), points.max(axis=0)), settings=settings)
    pc = points @ E[:3, :3].T + E[:3, 3]
    uv = pc[:, :2] / pc[:, 2:3] * [K[0, 0], K[1, 1]] + K[:2, 2]
    mask = np.zeros((settings.height, settings.width), np.uint8)
    cv2.fillConvexPoly(mask, cv2.convexHull(np.rint(uv).astype(np.int32)), 1)
    return mask.astype(bool)


@pytest.mark.parametrize("renderer", ["auto", "software"])
def test_view_writes_a_png_of_the_object(tmp_path, capsys, renderer):
    if renderer == "auto" and not offscreen_available():
        pytest.skip("Open3D's offscreen renderer cannot start here")
    mesh = _ellipsoid()
    path = tmp_path / "obj.stl"
    write_mesh(path, mesh)
    out = tmp_path / "view.png"
    rc = main(["view", str(path), "--out", str(out), "--width", "200", "--height", "160", "--renderer", renderer])
    assert rc == 0
    assert ("open3d renderer" if renderer == "auto" else "software renderer") in capsys.readouterr().out
    img = cv2.imread(str(out))
    assert img.shape == (160, 200, 3)
    got = np.any(img != 255, axis=2)
    want = _expected(np.asarray(mesh.vertices), ViewSettings(width=200, height=160))
    iou = (got & want).sum() / (got | want).sum()
    assert iou > 0.9
    assert 40 < img[got].mean() < 240  # shaded, not a black or white blob


def test_view_cloud_with_truth_colours(tmp_path, capsys):
    mesh = _ellipsoid()
    pc = mesh.sample_points_uniformly(5000)
    pts = np.asarray(pc.points)
    pts[: len(pts) // 2] *= 1.02  # half the points off the surface
    cloud_path = tmp_path / "cloud.ply"
    o3d.io.write_point_cloud(str(cloud_path), pc)
    truth = tmp_path / "truth.ply"
    write_mesh(truth, mesh)
    out = tmp_path / "err.png"
    rc = main(["view", str(cloud_path), "--out", str(out), "--width", "160", "--height", "120",
               "--renderer", "software", "--truth", str(truth)])
    assert rc == 0
    text = capsys.readouterr().out
    assert "distance to truth: mean" in text
    img = cv2.imread(str(out))
    assert img.shape == (120, 160 + 110, 3)  # colour bar appended
    assert f"wrote {out} ({160 + 110}x120, software renderer, scale bar " in text  # the size of the PNG written
    obj = img[:, :160][np.any(img[:, :160] != 255, axis=2)].astype(int)
    assert np.ptp(obj[:, 2] - obj[:, 0]) > 100  # both ends of the colour map appear


def test_view_errors(tmp_path, capsys):
    assert main(["view", str(tmp_path / "missing.ply"), "--out", str(tmp_path / "x.png")]) == 1
    assert "missing.ply: file not found" in capsys.readouterr().err
    (tmp_path / "empty.ply").write_text("ply\nformat ascii 1.0\nelement vertex 0\nend_header\n")
    assert main(["view", str(tmp_path / "empty.ply"), "--out", str(tmp_path / "x.png")]) == 1
    assert "no points" in capsys.readouterr().err
    assert not (tmp_path / "x.png").exists()


def test_view_leaves_out_infinite_points(tmp_path, caplog, capsys):
    pc = _ellipsoid().sample_points_uniformly(3000)
    pts = np.asarray(pc.points)
    pts[::15] = np.inf
    pts[1::15, 2] = np.nan
    path = tmp_path / "inf.ply"
    o3d.io.write_point_cloud(str(path), pc)
    out = tmp_path / "v.png"
    rc = main(["view", str(path), "--out", str(out), "--width", "120", "--height", "96", "--renderer", "software"])
    assert rc == 0
    assert any("left out 400 of 3000 points with a NaN or infinite coordinate" in r.getMessage()
               for r in caplog.records)
    img = cv2.imread(str(out))
    drawn = np.any(img != 255, axis=2)
    assert 0.05 < drawn.mean() < 0.9  # the object is there, not a blank picture
    pts[:] = np.inf
    o3d.io.write_point_cloud(str(path), pc)
    assert main(["view", str(path), "--out", str(tmp_path / "w.png"), "--renderer", "software"]) == 1
    assert f"{path}: none of its 3000 points has finite coordinates" in capsys.readouterr().err
    assert not (tmp_path / "w.png").exists()


def test_view_conditioning_map_of_a_rig(tmp_path, capsys):
    """``view --conditioning RIG``: the three panels, and the summary says that
    both coordinates place every lit pixel where rings alone leave gaps."""
    import json

    from ringscan.pipeline.formats.rig import default_rig, save_rig

    rig_path = tmp_path / "rig.json"
    save_rig(rig_path, default_rig(light_model="perspective"))
    out = tmp_path / "cond.png"
    assert main(["view", "--conditioning", str(rig_path), "--out", str(out), "--step", "16", "--device", "cpu"]) == 0
    summary = json.loads(capsys.readouterr().out.splitlines()[0])
    assert summary["both"]["placed"] > 0.999 and summary["rings"]["placed"] < summary["both"]["placed"]
    img = cv2.imread(str(out))
    assert img is not None and img.shape[1] > 3 * img.shape[0] / 2  # three panels side by side
    assert main(["view", "--out", str(tmp_path / "x.png")]) == 2
    assert "--conditioning" in capsys.readouterr().err
def test_view_conditioning_of_a_huge_camera_is_bounded(tmp_path, capsys):
    """A rig's 65536x65536 camera (4295 megapixels: before, accepted, and the map asked for 64 GiB) is refused
    by the rig's pixel bound; a 200-megapixel camera (accepted) needs a step that keeps the map within
    MAX_MAP_PIXELS, said before anything is computed."""
    import json

    from ringscan.pipeline.formats.rig import default_rig, rig_to_dict

    d = rig_to_dict(default_rig())
    rig_path = tmp_path / "rig.json"
    out = tmp_path / "cond.png"
    d["camera"].update(width=65536, height=65536)
    rig_path.write_text(json.dumps(d))
    assert main(["view", "--conditioning", str(rig_path), "--out", str(out), "--device", "cpu"]) == 1
    err = capsys.readouterr().err.strip()
    assert err == (f"ringscan view: error: {rig_path}: camera: 65536x65536 is 4295 megapixels: larger than the images "
                   "ringscan reads (200 megapixels)"), err
    d["camera"].update(width=16000, height=12500)  # 200 megapixels: step 10 gives 1600x1250, the 2 million allowed
    rig_path.write_text(json.dumps(d))
    assert main(["view", "--conditioning", str(rig_path), "--out", str(out), "--device", "cpu"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith(f"ringscan view: error: --step 4: the map of the 16000x12500 camera of {rig_path} would "
                          "evaluate more than 2000000 pixels (~1.5 GB); give --step 10 or more"), err
    assert not out.exists()
    from ringscan.pipeline.evaluate.conditioning import ConditioningSettings, compute_conditioning
    from ringscan.pipeline.formats.rig import load_rig

    with pytest.raises(ValueError, match=r"^conditioning: step 9 evaluates 1778x1389 pixels of the 16000x12500 camera: "
                                         r"more than the 2000000 a map may have \(~1.5 GB\); a step of 10 or more"):
        compute_conditioning(load_rig(rig_path), center=(511.5, 383.5), rho_range=(8.0, 380.0),
                             settings=ConditioningSettings(step=9), device="cpu")


def test_view_truth_takes_a_simulated_scan_too(tmp_path, capsys):
    from tests.support.tiny_scan import simulate_tiny_scan

    scan = simulate_tiny_scan(tmp_path / "scan")
    truth_mesh = o3d.io.read_triangle_mesh(str(scan.folder / scan.extra["truth"]["mesh"]))
    pc = truth_mesh.sample_points_uniformly(2000)
    cloud = tmp_path / "cloud.ply"
    o3d.io.write_point_cloud(str(cloud), pc)
    out = tmp_path / "t.png"
    assert main(["view", str(cloud), "--out", str(out), "--width", "80", "--height", "60", "--renderer", "software",
                 "--truth", str(scan.folder)]) == 0
    text = capsys.readouterr().out
    obj = text.split("distance to truth, object (")[1]
    n_obj = int(obj.split(" points")[0])
    n_floor = int(text.split("; floor (")[1].split(" points")[0])
    assert n_obj + n_floor == 2000 and n_obj > 1900  # the sphere rests on the floor: a few points touch it
    assert float(obj.split("mean ")[1].split(" mm")[0]) < 1e-3  # points sampled on the truth: on it


@pytest.fixture(scope="module")
def tiny_recon(tmp_path_factory):
    from ringscan.pipeline.reconstruct import reconstruct_scan
    from tests.support.tiny_scan import simulate_tiny_scan

    root = tmp_path_factory.mktemp("tiny")
    scan = simulate_tiny_scan(root / "scan")
    reconstruct_scan(scan, root / "recon", device="cpu", progress=False)
    return scan, root / "recon"


def test_a_views_cloud_is_seen_from_its_own_camera(tiny_recon, tmp_path, capsys):
    from ringscan.pipeline.formats.ply import read_ply

    scan, recon = tiny_recon
    out = tmp_path / "own.png"
    cam = scan.rig.camera
    assert main(["view", str(recon / "view_000.ply"), "--out", str(out), "--width", str(cam.width),
                 "--renderer", "software", "--point-size", "1", "--no-scale-bar"]) == 0
    assert f"({cam.width}x{cam.height}, software renderer, seen from view_000's camera)" in capsys.readouterr().out
    img = cv2.imread(str(out))
    from ringscan.pipeline.preview.render import HATCH_BGR

    # what is not the points: the hatch where nothing was decoded, and its key in the upper left corner
    drawn = np.any(img != 255, axis=2) & ~np.all(img == HATCH_BGR, axis=2)
    drawn[:30, :200] = False
    ply = read_ply(recon / "view_000.ply")
    seen = np.zeros_like(drawn)
    seen[np.clip(np.rint(ply["v"]).astype(int), 0, cam.height - 1),
         np.clip(np.rint(ply["u"]).astype(int), 0, cam.width - 1)] = True
    near = cv2.dilate(seen.astype(np.uint8), np.ones((5, 5), np.uint8)).astype(bool)
    # The render lands on the pixels the camera saw the points at (lens distortion aside).
    assert drawn.sum() > 0.5 * seen.sum()
    assert (drawn & near).sum() / drawn.sum() > 0.95
    # Shaded by the estimated normals: not one flat colour.
    assert np.std(img[drawn].astype(float).mean(axis=1)) > 5


def test_view_colours_a_cloud_by_a_field_with_a_colour_bar(tiny_recon, tmp_path, capsys):
    _, recon = tiny_recon
    out = tmp_path / "conf.png"
    assert main(["view", str(recon / "view_000.ply"), "--out", str(out), "--width", "160", "--camera", "orbit",
                 "--height", "120", "--renderer", "software", "--color-by", "confidence"]) == 0
    img = cv2.imread(str(out))
    assert img.shape == (120, 160 + 110, 3)
    obj = img[:, :160][np.any(img[:, :160] != 255, axis=2)].astype(int)
    assert np.ptp(obj[:, 2] - obj[:, 0]) > 60  # several colours of the map
    capsys.readouterr()
    with pytest.raises(SystemExit):
        main(["view", str(recon / "view_000.ply"), "--out", str(out), "--color-by", "nope"])
    assert main(["view", str(recon / "view_000.ply"), "--out", str(out), "--color-by", "error"]) == 2
    assert "--color-by error needs --truth" in capsys.readouterr().err


def test_scale_bar_is_a_round_length_true_at_the_points_depth(tmp_path, capsys):
    from ringscan.pipeline.preview.render import scale_bar_mm

    pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.array([[0.0, 0, 500], [10, 0, 500], [0, 10, 500]])))
    K = np.array([[1000.0, 0, 479.5], [0, 1000.0, 359.5], [0, 0, 1]])
    assert scale_bar_mm([pc], K, np.eye(4), 960) == (50.0, 100.0)  # 2 px/mm at 500 mm: 96 mm wanted -> 50 mm
    mesh = _ellipsoid()  # 40 mm long
    path = tmp_path / "e.stl"
    write_mesh(path, mesh)
    with_bar, without = tmp_path / "a.png", tmp_path / "b.png"
    args = ["view", str(path), "--width", "320", "--height", "240", "--renderer", "software"]
    assert main([*args, "--out", str(with_bar)]) == 0
    mm = float(capsys.readouterr().out.split("scale bar ")[1].split(" mm")[0])
    assert mm in (1, 2, 5, 10, 20, 50)
    assert main([*args, "--out", str(without), "--no-scale-bar"]) == 0
    a, b = cv2.imread(str(with_bar)), cv2.imread(str(without))
    corner = (slice(240 - 30, 240), slice(0, 100))  # the lower left corner, clear of the object
    assert (a[corner] < 128).any() and (b[corner] == 255).all()
