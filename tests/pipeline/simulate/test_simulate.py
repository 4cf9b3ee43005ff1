"""The virtual rig: radiometry, turntable, truth files, determinism, bad input."""

import dataclasses
import math

import numpy as np
import open3d as o3d
import pytest

from ringscan.pipeline.codecs.render import render_frame
from ringscan.pipeline.formats.errors import FormatError
from ringscan.pipeline.formats.images import read_image
from ringscan.pipeline.formats.patterns import frame_names
from ringscan.pipeline.formats.rig import turntable_transform
from ringscan.pipeline.formats.scan import load_scan, read_view_frames
from ringscan.pipeline.simulate.scan import simulate_scan
from ringscan.pipeline.simulate.scenes import make_scene
from ringscan.pipeline.simulate.truth import load_truth
from ringscan.pipeline.simulate.virtual_rig import RenderSettings, VirtualRig, view_angles
from tests.support.simulate_rig import PH, PW, S, small_rig, small_spec


CLEAN = RenderSettings(supersample=1, ambient=0.0, albedo=1.0, defocus_px=0.0, noise=0.0, bit_depth=16)


def test_pixel_brightness_follows_the_frame_under_parallel_light(device):
    """A pixel seeing (x, y, 0) records the frame at (x/s + a_u, y/s + a_v) (gamma 1, no noise).

    Without defocus each projector pixel is a sharp uniform square: the value is
    that of the projector pixel the point falls in.
    """
    vr = VirtualRig(small_rig(gamma=1.0), "plane", settings=CLEAN, device=device)
    vp, up = np.mgrid[0:PH, 0:PW]
    frame = np.clip(128 + 100 * np.sin(up / 9.0) * np.cos(vp / 6.0), 0, 255).astype(np.uint8)
    img = vr.render(frame)
    assert img.dtype == np.uint16 and img.shape == (256, 320)
    tr = vr.truth()
    pts = tr["points"].astype(np.float64)
    u_p, v_p = pts[..., 0] / S + 127.5, pts[..., 1] / S + 95.5
    inside = (u_p > 0) & (u_p < PW - 1) & (v_p > 0) & (v_p < PH - 1)
    clear = inside & (np.abs(u_p - np.floor(u_p) - 0.5) > 1e-3) & (np.abs(v_p - np.floor(v_p) - 0.5) > 1e-3)
    expect = frame[np.rint(v_p[clear]).astype(int), np.rint(u_p[clear]).astype(int)] / 255.0
    assert clear.sum() > 5000
    assert np.abs(img[clear] / 65535.0 - 0.9 * expect).max() < 1e-4             # exposure 0.9
    assert tr["lit"][inside].all()                                              # lit inside the image
    assert not tr["lit"][(u_p < -1) | (u_p > PW) | (v_p < -1) | (v_p > PH)].any()


def test_exposure_and_camera_gamma():
    """White on the plane (albedo 1, facing the light) records exposure * full scale; gamma bends mid-grey."""
    st = dataclasses.replace(CLEAN, ambient=0.05, bit_depth=8)
    vr = VirtualRig(small_rig(gamma=2.2), "plane", settings=st, device="cpu")
    lit = vr.truth()["lit"]
    white = vr.render(np.full((PH, PW), 255, np.uint8))
    assert np.all(np.abs(white[lit].astype(int) - round(0.9 * 255)) <= 1)
    black = vr.render(np.zeros((PH, PW), np.uint8))
    amb = 255 * 0.9 * (0.05 / 1.05) ** (1 / 2.2)
    assert np.all(np.abs(black[lit] - amb) <= 1)
    grey = vr.render(np.full((PH, PW), 128, np.uint8))
    expect = 255 * 0.9 * ((0.05 + 128 / 255) / 1.05) ** (1 / 2.2)
    assert np.all(np.abs(grey[lit] - expect) <= 1)


def test_light_gamma_and_defocus():
    vr = VirtualRig(small_rig(light_gamma=2.0), "plane", settings=RenderSettings(defocus_px=1.5), device="cpu")
    k = vr.emitted_upsample
    f = np.zeros((PH, PW), np.uint8)
    f[96, 128] = 128
    e = vr.emitted(f).astype(np.float64)
    assert e.shape == (PH * k, PW * k) and k == 4
    assert e.sum() / k ** 2 == pytest.approx((128 / 255) ** 2, rel=1e-3)   # response, energy kept
    vv, uu = np.mgrid[0:PH * k, 0:PW * k]
    u = (uu + 0.5) / k - 0.5
    var_u = (e * (u - 128) ** 2).sum() / e.sum()
    assert var_u == pytest.approx(1.5 ** 2 + 1 / 12, rel=0.01)            # pixel square * Gaussian
    with pytest.raises(ValueError, match="frame"):
        vr.render(np.zeros((10, 10), np.uint8))
    with pytest.raises(ValueError, match="uint8"):
        vr.render(np.zeros((PH, PW), np.float32))


@pytest.mark.parametrize("edge", [100.5, 100.62, 100.8, 101.3])
def test_defocused_edge_crosses_half_where_the_blurred_pixels_do(edge):
    """The emitted light is the projector's sharp pixel squares blurred by a Gaussian:
    its 50 % level matches that model computed directly (not the ideal edge: an
    edge inside a pixel is shown as a grey pixel)."""
    sigma = 0.7
    vr = VirtualRig(small_rig(), "plane", settings=RenderSettings(defocus_px=sigma), device="cpu")
    cov = np.clip(np.arange(PW) + 0.5 - edge, 0, 1)
    f = np.tile(np.rint(cov * 255).astype(np.uint8), (PH, 1))
    row = vr.emitted(f)[321].astype(np.float64)
    uf = (np.arange(row.size) + 0.5) / 4 - 0.5
    i = np.nonzero((row[:-1] < 0.5) & (row[1:] >= 0.5))[0][0]
    x = uf[i] + (0.5 - row[i]) / (row[i + 1] - row[i]) * 0.25

    p = f[0] / 255.0
    cdf = np.vectorize(lambda z: 0.5 * (1 + math.erf(z / (sigma * math.sqrt(2)))))
    j = np.arange(PW)

    def model(t):
        return float((p * (cdf(t - j + 0.5) - cdf(t - j - 0.5))).sum())

    lo, hi = edge - 1.5, edge + 1.5                                          # bisection on the model
    for _ in range(50):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if model(mid) < 0.5 else (lo, mid)
    assert abs(x - lo) < 2e-3
    assert abs(x - edge) < 0.035                                             # within 0.035 px of the ideal edge


def test_turntable_rotates_truth_points():
    rig = small_rig()
    vr = VirtualRig(rig, make_scene("terrain", size_mm=60.0), settings=dataclasses.replace(CLEAN), device="cpu")
    p0 = vr.truth()["points"]
    vr.set_turntable(90.0)
    assert vr.turntable_deg == 90.0
    p90 = vr.truth()["points"].astype(np.float64)
    obj = p90[p90[..., 2] > 1.0]
    assert obj.shape[0] > 2000
    # Turned back by -90 deg about z, every point lies on the mesh at angle 0.
    T = turntable_transform(rig.turntable, -90.0)
    R, t = T[:3, :3], T[:3, 3]
    assert np.allclose(R, [[0, 1, 0], [-1, 0, 0], [0, 0, 1]], atol=1e-12)
    back = obj @ R.T + t
    m = o3d.t.geometry.TriangleMesh()
    m.vertex.positions = o3d.core.Tensor(vr.scene.vertices.astype(np.float32))
    m.triangle.indices = o3d.core.Tensor(vr.scene.faces)
    rs = o3d.t.geometry.RaycastingScene()
    rs.add_triangles(m)
    dist = rs.compute_distance(o3d.core.Tensor(back.astype(np.float32))).numpy()
    assert np.percentile(dist, 99.9) < 2e-3
    assert not np.allclose(np.nan_to_num(p0), np.nan_to_num(p90))            # the view changed
    assert np.allclose(vr.object_vertices(), vr.scene.vertices @ R, atol=1e-9)


def test_simulate_scan_writes_frames_and_truth(tmp_path):
    rig = small_rig()
    spec = small_spec()
    scan = simulate_scan(tmp_path / "s", scene="cube", rig=rig, patterns=spec, views=2,
                         settings=RenderSettings(supersample=1), device="cpu", progress=False, size_mm=40.0)
    again = load_scan(tmp_path / "s")
    assert [v.name for v in again.views] == ["view_000", "view_001"]
    assert [v.turntable_deg for v in again.views] == [0.0, 180.0]
    names = frame_names(spec)
    assert set(again.views[0].frames) == set(names)
    assert again.views[1].frames["white"] == "view_001/white.png"
    st = read_view_frames(again, again.views[1])
    assert st.shape == (len(names), 256, 320) and st.dtype == np.uint8
    truth = load_truth(scan)
    assert truth.scene == "cube" and truth.reference_plane_z == 0.0
    assert truth.settings["supersample"] == 1 and truth.settings["noise"] == 1.5
    cube = make_scene("cube", size_mm=40.0)
    assert np.abs(truth.vertices - cube.vertices).max() < 1e-9 and np.array_equal(truth.faces, cube.faces)
    v180, _ = truth.mesh_at(180.0)
    assert np.allclose(v180[:, :2], -cube.vertices[:, :2]) and np.allclose(v180[:, 2], cube.vertices[:, 2])
    # The depth and lit files are the renderer's truth for that view.
    vr = VirtualRig(rig, cube, settings=RenderSettings(supersample=1), device="cpu")
    vr.set_turntable(180.0)
    tr = vr.truth()
    d = truth.depth("view_001")
    assert d.dtype == np.float32 and np.array_equal(np.isnan(d), np.isnan(tr["depth"]))
    assert np.nanmax(np.abs(d - tr["depth"])) == 0.0
    assert np.array_equal(truth.lit("view_001"), tr["lit"])
    assert set(np.unique(read_image(tmp_path / "s" / "truth" / "view_001_lit.png"))) <= {0, 255}
    # The frames show the truth: lit pixels are brighter under white than under black.
    white, black = st[names.index("white")], st[names.index("black")]
    assert np.median(white[tr["lit"]].astype(int) - black[tr["lit"]]) > 100
    with pytest.raises(ValueError, match="no view"):
        truth.depth("view_009")


def test_determinism_and_16_bit(tmp_path):
    st = RenderSettings(supersample=1, seed=3)
    vr = VirtualRig(small_rig(), "sphere", settings=st, device="cpu")
    f = render_frame(small_spec(), "gray_1")
    a, b = vr.render(f, seed=11), vr.render(f, seed=11)
    assert np.array_equal(a, b)
    c, d = vr.render(f), vr.render(f)                    # fresh noise per call, repeatable order
    assert not np.array_equal(c, d)
    vr2 = VirtualRig(small_rig(), "sphere", settings=st, device="cpu")
    assert np.array_equal(vr2.render(f), c)
    n16 = dataclasses.replace(st, bit_depth=16, noise=0.0)
    n8 = dataclasses.replace(st, noise=0.0)
    i16 = VirtualRig(small_rig(), "sphere", settings=n16, device="cpu").render(f)
    i8 = VirtualRig(small_rig(), "sphere", settings=n8, device="cpu").render(f)
    assert i16.dtype == np.uint16 and i16.max() > 255
    assert np.abs(i16 / 257.0 - i8).max() <= 0.51
    s1 = simulate_scan(tmp_path / "a", scene="plane", rig=small_rig(), patterns=small_spec(sector_bits=0),
                       settings=st, device="cpu", progress=False)
    s2 = simulate_scan(tmp_path / "b", scene="plane", rig=small_rig(), patterns=small_spec(sector_bits=0),
                       settings=st, device="cpu", progress=False)
    assert np.array_equal(read_view_frames(s1, s1.views[0]), read_view_frames(s2, s2.views[0]))
    assert load_truth(s1).faces.shape == (0, 3)                               # plane: an empty mesh
    assert (s1.folder / "truth" / "object.ply").is_file()


def test_perspective_light_smoke():
    rig = small_rig(light_model="perspective")
    vr = VirtualRig(rig, make_scene("sphere", size_mm=50.0), settings=RenderSettings(supersample=1), device="cpu")
    tr = vr.truth()
    assert 0.2 < tr["lit"].mean() < 1.0
    white = vr.render(np.full((PH, PW), 255, np.uint8), seed=1)
    black = vr.render(np.zeros((PH, PW), np.uint8), seed=1)
    assert np.median(white[tr["lit"]].astype(int) - black[tr["lit"]]) > 100
    assert np.all(np.abs(white[~tr["lit"]].astype(int) - black[~tr["lit"]]) <= 12)   # noise only


def test_bad_input(tmp_path):
    spec = small_spec()
    with pytest.raises(ValueError, match="supersample"):
        RenderSettings(supersample=0)
    with pytest.raises(ValueError, match="bit_depth"):
        RenderSettings(bit_depth=12)
    with pytest.raises(ValueError, match="albedo"):
        RenderSettings(albedo=1.5)
    with pytest.raises(ValueError, match="noise"):
        RenderSettings(noise=-1)
    with pytest.raises(ValueError, match="unknown field.*gain"):
        RenderSettings.from_dict({"gain": 2})
    assert RenderSettings.from_dict(RenderSettings(seed=4).to_dict()) == RenderSettings(seed=4)
    with pytest.raises(ValueError, match="'blob'.*unknown"):
        simulate_scan(tmp_path / "x", scene="blob", rig=small_rig(), patterns=spec, progress=False)
    bad = tmp_path / "broken.ply"
    bad.write_bytes(b"ply\nformat ascii 1.0\nelement vertex 3\nend_header\n1 2\n")
    with pytest.raises(FormatError, match="broken.ply"):
        simulate_scan(tmp_path / "x", scene=bad, rig=small_rig(), patterns=spec, progress=False)
    with pytest.raises(ValueError, match="no turntable"):
        simulate_scan(tmp_path / "x", scene="plane", rig=small_rig(turntable=False), patterns=spec, views=2,
                      progress=False)
    with pytest.raises(ValueError, match="views"):
        view_angles(0)
    with pytest.raises(ValueError, match="projector_size"):
        VirtualRig(small_rig(), "plane", projector_size=(100, 100))
    s = simulate_scan(tmp_path / "y", scene="plane", rig=small_rig(), patterns=spec, progress=False,
                      settings=RenderSettings(supersample=1))
    assert load_truth(s).views == {"view_000": {"depth": "truth/view_000_depth.tiff",
                                                "lit": "truth/view_000_lit.png"}}
    js = tmp_path / "y" / "scan.json"
    js.write_text(js.read_text().replace('"truth"', '"other"'))
    with pytest.raises(FormatError, match="no 'truth'"):
        load_truth(tmp_path / "y")
    assert view_angles(4) == (0.0, 90.0, 180.0, 270.0)
    assert math.isclose(turntable_transform(None, 360.0)[0, 0], 1.0)
