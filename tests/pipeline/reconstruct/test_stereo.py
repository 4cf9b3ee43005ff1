"""Two cameras end to end on the virtual rig: both cameras decode, camera 1's samples
are matched in camera 2 by projector coordinate (checked against the truth of the
rendered sphere), the points of camera-camera, camera-projector and all three rays
against the truth mesh, the uncalibrated projector, and the epipolar check of a rig
whose extrinsics are off."""

import dataclasses

import cv2
import numpy as np
import pytest

from ringscan.pipeline.evaluate.metrics import evaluate_recon
from ringscan.pipeline.formats.errors import FormatError
from ringscan.pipeline.formats.ply import read_ply
from ringscan.pipeline.formats.scan import load_scan, save_scan
from ringscan.pipeline.reconstruct.scan import reconstruct_scan
from ringscan.pipeline.reconstruct.settings import ReconstructSettings, StereoSettings
from ringscan.pipeline.reconstruct.stereo import epipolar_distances, match_view
from ringscan.pipeline.reconstruct.view import reconstruct_view
from tests.support.two_camera_scan import simulate_two_camera_scan, true_uv2


def _rays(r):
    return ReconstructSettings(stereo=StereoSettings(rays=r))


@pytest.fixture(scope="module")
def stereo_scan(tmp_path_factory):
    return simulate_two_camera_scan(tmp_path_factory.mktemp("stereo") / "scan")


def test_matches_land_where_camera_2_sees_the_point(stereo_scan):
    scan = stereo_scan
    m = match_view(scan, scan.views[0], device="cpu")
    assert len(m) > 0.5 * m.stats["samples_camera1"] and m.stats["matches"] == len(m)
    # truth: camera 1's depth map (bilinear at uv1) -> the point -> camera 2
    keep, uv2 = true_uv2(scan, m)
    rig = scan.rig
    err = np.linalg.norm(m.uv2[keep] - uv2, axis=1)
    assert keep.mean() > 0.95 and np.median(err) < 0.1, np.median(err)  # camera px (0.65 mm pixels)
    # the rig fits: the matches lie on their epipolar lines
    assert np.median(epipolar_distances(rig, m.uv1, m.uv2)) < 0.1
    assert np.all(m.sigma1 > 0) and np.all(m.sigma2 > 0) and np.all(m.sigma_proj > 0)
    assert m.proj.shape == (len(m), 2) and m.uv1.shape == m.uv2.shape


def test_the_epipolar_check_reads_an_even_stride_of_a_large_views_matches(stereo_scan, monkeypatch):
    """Beyond EPIPOLAR_CHECK_MATCHES the check reads every k-th match (k the least that keeps it under): its
    median and p95 are those of exactly those matches' distances, and near the whole view's."""
    import warp as wp

    import ringscan.pipeline.reconstruct.stereo as stereo

    scan = stereo_scan
    m = match_view(scan, scan.views[0], device="cpu")
    d = epipolar_distances(scan.rig, m.uv1, m.uv2)
    n = len(m)
    uv = tuple(wp.array(a.astype(np.float32), dtype=wp.vec2, device="cpu") for a in (m.uv1, m.uv2))
    whole = stereo.epipolar_check(scan.rig, m, uv=uv)
    assert whole["matches"] == n
    monkeypatch.setattr(stereo, "EPIPOLAR_CHECK_MATCHES", n // 7)
    part = stereo.epipolar_check(scan.rig, m, uv=uv)
    every = -(-n // (n // 7))
    sub = d[::every]
    assert part["matches"] == sub.size <= n // 7 and every > 1
    # the kernel's float32 distances: within 1e-3 px of the host's float64 (epipolar_distances' docstring)
    assert abs(part["epipolar_px_median"] - np.median(sub)) < 1e-3
    assert abs(part["epipolar_px_p95"] - np.percentile(sub, 95)) < 1e-3
    assert abs(part["epipolar_px_median"] - whole["epipolar_px_median"]) < 0.1 * whole["epipolar_px_median"]


def test_camera_camera_camera_projector_and_all_three(stereo_scan, tmp_path):
    out = {}
    for rays in ("camera-projector", "camera-camera", "all", "auto"):
        rep = reconstruct_scan(stereo_scan, tmp_path / rays, settings=_rays(rays), progress=False)
        v = rep["views"][0]
        assert v["rays"] == (rays if rays != "auto" else "all")
        ev = evaluate_recon(tmp_path / rays, stereo_scan)
        out[rays] = (ev["all"]["median_mm"], ev["views"]["view_000"]["coverage"], v)
    for rays, (med, cov, v) in out.items():
        assert med < 0.05, (rays, med)
        assert v["calibration_check"]["fits"], v["calibration_check"]
    cc, au = out["camera-camera"][2], out["auto"][2]
    assert cc["calibration_check"]["kind"] == "epipolar" and cc["calibration_check"]["median_px"] < 0.3
    assert out["camera-projector"][2]["calibration_check"]["kind"] == "ray-ray"
    assert cc["dropped"]["unmatched"] > 0 and au["dropped"]["unmatched"] == 0  # auto falls back
    assert out["auto"][1] > out["camera-camera"][1]
    assert out["all"][0] <= 1.1 * out["camera-camera"][0]
    ply = read_ply(tmp_path / "all" / "view_000.ply")
    assert "residual" in ply and np.median(ply["residual"]) < 0.5


def test_uncalibrated_projector_works_camera_to_camera(stereo_scan, tmp_path):
    folder = tmp_path / "scan"
    import shutil
    shutil.copytree(stereo_scan.folder, folder)
    from ringscan.pipeline.formats.rig import UncalibratedLight
    scan = load_scan(folder)
    li = scan.rig.light
    save_scan(dataclasses.replace(scan, rig=dataclasses.replace(scan.rig, light=UncalibratedLight(
        width=li.width, height=li.height, gamma=li.gamma)), rig_ref=None))
    scan = load_scan(folder)
    rep = reconstruct_scan(scan, tmp_path / "rec", progress=False)
    assert rep["views"][0]["rays"] == "camera-camera"
    # evaluated against the calibrated twin (evaluate reads the projector for its coverage mask)
    assert evaluate_recon(tmp_path / "rec", stereo_scan)["all"]["median_mm"] < 0.05
    with pytest.raises(FormatError, match="not calibrated"):
        reconstruct_view(scan, scan.views[0], settings=_rays("all"), device="cpu")
    with pytest.raises(FormatError, match="not calibrated"):
        reconstruct_view(scan, scan.views[0], settings=_rays("camera-projector"), device="cpu")


def test_rotated_extrinsics_warn(stereo_scan, tmp_path, caplog):
    rig = stereo_scan.rig
    c2 = rig.camera2
    # the camera-1-to-camera-2 rotation off by 2 degrees, its translation kept (as in
    # an OpenCV stereo file whose R does not fit): X2 = dR R_rel X1 + T_rel
    c1 = rig.camera
    dR = cv2.Rodrigues(np.array([0.0, np.radians(2.0), 0.0]))[0]
    R_rel = c2.R @ c1.R.T
    T_rel = c2.t - R_rel @ c1.t
    R_bad = dR @ R_rel
    c2_bad = dataclasses.replace(c2, R=R_bad @ c1.R, t=R_bad @ c1.t + T_rel)
    bad = dataclasses.replace(stereo_scan, rig=dataclasses.replace(rig, camera2=c2_bad))
    m = match_view(stereo_scan, stereo_scan.views[0], device="cpu")
    good_d = np.median(epipolar_distances(rig, m.uv1, m.uv2))
    bad_d = np.median(epipolar_distances(bad.rig, m.uv1, m.uv2))
    assert good_d < 0.3 and bad_d > 3.0, (good_d, bad_d)
    with caplog.at_level("WARNING"):
        cloud = reconstruct_view(bad, bad.views[0], settings=_rays("camera-camera"), device="cpu")
    chk = cloud.stats["calibration_check"]
    assert not chk["fits"] and chk["median_px"] > 3.0
    # the cloud is still made (worse), not dropped as inconsistent
    assert cloud.stats["points"] > 0.5 * cloud.stats["stereo"]["matches"]
    assert "does not fit the images" in caplog.text


def test_one_camera_view_refuses_two_camera_rays(tmp_path):
    from tests.support.tiny_scan import simulate_tiny_scan
    scan = simulate_tiny_scan(tmp_path / "tiny")
    with pytest.raises(FormatError, match="needs a two-camera view"):
        reconstruct_view(scan, scan.views[0], settings=_rays("camera-camera"), device="cpu")
    with pytest.raises(FormatError, match="not a two-camera view"):
        match_view(scan, scan.views[0], device="cpu")


def test_imported_integer_gray_code_is_matched_sub_pixel(tmp_path):
    # every pixel's projector pixel as an OpenCV Gray code decodes it (integer codes):
    # camera to camera, camera 1's codes read from their 5 x 5 neighbours and the local fit
    # over camera 2's beat the projector ray of one rounded code by half, and all three rays
    # beat both
    from ringscan.pipeline.evaluate.metrics import point_distances, truth_surface
    from tests.support.two_camera_scan import simulate_decoded_two_camera_scan

    scan = simulate_decoded_two_camera_scan(tmp_path / "scan", integer=True)
    mesh = truth_surface(scan, 0.0)
    med = {}
    for rays in ("camera-projector", "camera-camera", "all"):
        cloud = reconstruct_view(scan, scan.views[0], settings=_rays(rays))  # reconstruct_scan's points, in memory
        v = cloud.stats
        d = point_distances(mesh, cloud.points.astype(np.float64))
        med[rays] = float(np.median(d))
        assert v["rays"] == rays and v["points"] > (0.99 if rays == "camera-projector" else 0.7) * v["samples"]
    # measured 0.047 / 0.018 / 0.015 mm (before camera 1's codes were read from their neighbours,
    # camera-camera was 0.039 and all three 0.025: the rounded code of camera 1's pixel was as far
    # off as camera 2's fit averaged away); the bars leave ~25 % for the noise
    assert med["camera-camera"] < 0.5 * med["camera-projector"], med
    assert med["all"] < 0.95 * med["camera-camera"], med
    assert med["all"] < 0.02, med  # mm, 0.65 mm camera pixels


def test_auto_fallback_places_points_as_one_camera_does(stereo_scan):
    """--rays auto on a rig whose projector misses by more than the decode's errors: the camera-1 samples camera 2
    does not match fall back to camera-projector with the calibration floor, exactly where a one-camera
    reconstruction of the same scan places them (their sigmas wider by the miss the two cameras see)."""
    rig = stereo_scan.rig
    li = rig.light
    dR = cv2.Rodrigues(np.array([0.0, 0.0, np.radians(0.3)]))[0]  # the projector turned 0.3 deg about its axis
    off = dataclasses.replace(stereo_scan, rig=dataclasses.replace(rig, light=dataclasses.replace(li, R=dR @ li.R)))
    auto = reconstruct_view(off, off.views[0], settings=_rays("auto"), device="cpu")
    one = reconstruct_view(off, off.views[0], settings=_rays("camera-projector"), device="cpu")
    assert auto.stats["rays"] == "all" and one.stats["rays"] == "camera-projector"
    cal = one.stats["calibration"]
    assert cal["floor_applied"] and cal["floor_px"] > 0, cal
    assert auto.stats["calibration"] == cal
    m = match_view(off, off.views[0], device="cpu")
    matched = {(float(u), float(v)) for u, v in m.uv1}
    by_uv = {(float(u), float(v)): i for i, (u, v) in enumerate(one.uv)}
    fb = [(i, by_uv[(float(u), float(v))]) for i, (u, v) in enumerate(auto.uv)
          if (float(u), float(v)) not in matched and (float(u), float(v)) in by_uv]
    assert len(fb) > 0.5 * auto.stats["stereo"]["fallback_camera_projector"] and len(fb) > 500, len(fb)
    a, b = np.array([i for i, _ in fb]), np.array([j for _, j in fb])
    assert np.array_equal(auto.points[a], one.points[b]) and np.array_equal(auto.residual[a], one.residual[b])
    # the two cameras see the projector miss along camera 1's rays too (which no camera-projector check sees):
    # the fallback points' sigmas take that miss in depth, never narrower
    assert auto.stats["stereo"]["projector_check"]["floor_applied"]
    assert np.all(auto.sigma[a] >= one.sigma[b]) and np.median(auto.sigma[a] / one.sigma[b]) > 1.2


def test_predicted_match_sigmas_are_the_errors_scale(stereo_scan):
    """The matches' camera-2 errors against the truth over their predicted sqrt(sigma1^2 + sigma2^2): a MAD near
    1 per axis (it was ~2 while the sigmas held the decode's noise alone; benchmarks/stereo_rays.py)."""
    scan = stereo_scan
    m = match_view(scan, scan.views[0], device="cpu")
    keep, uv2 = true_uv2(scan, m)
    e = m.uv2[keep] - uv2
    zn = e / np.hypot(m.sigma1, m.sigma2)[keep][:, None]
    mad = 1.4826 * np.median(np.abs(zn - np.median(zn, axis=0)), axis=0)
    assert np.all((0.8 < mad) & (mad < 1.3)), mad
    assert 0.55 < np.mean(np.abs(zn) < 1) < 0.8


def test_matches_whose_decode_errs_beyond_its_sigmas_are_widened_by_their_epipolar_distances(tmp_path, monkeypatch):
    """Both cameras' decoded maps carry an error their sigmas do not hold: 0.15 projector px (RMS) added to
    every coordinate, alike over ~3 camera px (a pixel's neighbours share it, as where a camera pixel spans
    several projector pixels and reads its place from the same coarser stripes' boundaries: the matcher's fit
    through camera 2's neighbours takes it for the surface), where the contrast predicts ~0.02 px. The matches'
    distances from their epipolar lines measure it, and the points' sigmas then mean what they say (median |e|/sigma within 0.4-1.2, <= 5 % beyond
    3 sigma: the issue's bounds). Without the fit (monkeypatched out) the same points are over-confident; with
    three rays alike (the query's projector point widened as camera 1's code), and the points closer."""
    import shutil

    from ringscan.pipeline.formats.images import read_image, write_image
    from ringscan.pipeline.reconstruct import stereo
    from tests.support.two_camera_scan import simulate_decoded_two_camera_scan

    exact = simulate_decoded_two_camera_scan(tmp_path / "exact", integer=False)
    folder = tmp_path / "noisy"
    shutil.copytree(exact.folder, folder)
    rng = np.random.default_rng(11)
    scale = exact.patterns.scale
    view = exact.views[0]
    for frames in (view.frames, view.camera2.frames):
        for name in ("proj_u", "proj_v"):
            q = read_image(folder / frames[name]).astype(np.float64)
            err = cv2.GaussianBlur(rng.normal(0.0, 1.0, q.shape), (0, 0), 3.0)
            noisy = np.round(q + err * (0.15 * scale / np.std(err)))
            write_image(folder / frames[name], np.where(q > 0, np.clip(noisy, 1, 65535), 0).astype(np.uint16))
    scan = load_scan(folder)

    def run(rays, out):
        rep = reconstruct_scan(scan, tmp_path / out, settings=_rays(rays), progress=False)
        figures = evaluate_recon(tmp_path / out, scan)["all"]
        return rep["views"][0], figures, read_ply(tmp_path / out / "view_000.ply")

    v, fitted, _ = run("camera-camera", "fitted")
    model = v["stereo"]["error_model"]
    assert model["k"] > 1.2 and model["z_median"] > 1.2  # the maps' error, measured
    assert 0.4 < fitted["sigma"]["median_ratio"] < 1.2 and fitted["sigma"]["beyond_3"] <= 0.05, fitted["sigma"]
    with monkeypatch.context() as mp:
        mp.setattr(stereo, "match_error_model", lambda *a, **k: {})
        _, raw, _ = run("camera-camera", "raw")
    # (each point's own chi widens the worst of them: kernels.stereo_rays.widen_by_chi; the rest stay narrow)
    assert raw["sigma"]["median_ratio"] > 0.9 and raw["sigma"]["beyond_3"] > 0.1, raw["sigma"]
    assert abs(fitted["median_mm"] - raw["median_mm"]) < 0.1 * raw["median_mm"]  # the points stay put

    v3, three, _ = run("all", "three")
    model3 = v3["stereo"]["error_model"]
    assert model3["k"] == model["k"] and model3["floor_px"] == model["floor_px"]  # the same matches, the same fit
    assert 0.4 < three["sigma"]["median_ratio"] < 1.2 and three["sigma"]["beyond_3"] <= 0.05, three["sigma"]
    with monkeypatch.context() as mp:
        mp.setattr(stereo, "match_error_model", lambda *a, **k: {})
        _, raw3, _ = run("all", "three_raw")
    # (the projector's check still discounts its ray a little there: the codes' errors unfitted, it misses)
    assert raw3["sigma"]["median_ratio"] > 0.9 and raw3["sigma"]["beyond_3"] > 0.05, raw3["sigma"]
    # the projector's ray adds what camera 2's lacks, and widened with both codes it keeps its weight
    assert three["median_mm"] < 0.8 * fitted["median_mm"] and three["median_mm"] < raw3["median_mm"]


def test_the_matches_tile_factors_widen_sigmas_and_barely_move_the_points(stereo_scan, tmp_path, monkeypatch):
    """Camera 1's tiles whose matches disagree more than the view's fit (``stereo.error_model.regions``) widen
    both cameras' sigmas of a match alike (and, with three rays, the projector point's): a factor of 4 in
    variance planted on the left half of camera 1 doubles those points' sigmas (a little less where camera 1's
    pixel ray, which no tile widens, holds a share), leaves every other point as it was, and moves none by
    more than a fifth of its sigma (the pixel ray's weight against the others': 0.07 camera to camera, 0.19
    with three rays here)."""
    from ringscan.pipeline.reconstruct import stereo

    fit = stereo.match_error_model

    def with_tiles(scales):
        def fitted(*a, **k):  # the view's own fit, its tiles replaced
            return {**fit(*a, **k), "regions": {"tile_px": 32, "scales": scales}}
        return fitted

    left = [[tx, ty, 4.0] for tx in range(5) for ty in range(8)]  # u < 160
    # (the points' own chi, which a tile's wider sigmas shrink, left out: the tiles alone)
    monkeypatch.setattr("ringscan.kernels.stereo_rays.widen_by_chi", lambda tri, **k: tri)
    for rays in ("camera-camera", "all"):
        clouds = {}
        for name, scales in (("none", []), ("left", left)):
            with monkeypatch.context() as mp:
                mp.setattr(stereo, "match_error_model", with_tiles(scales))
                reconstruct_scan(stereo_scan, tmp_path / f"{name}_{rays}", settings=_rays(rays), progress=False)
            clouds[name] = read_ply(tmp_path / f"{name}_{rays}" / "view_000.ply")
        plain, wide = clouds["none"], clouds["left"]
        moved = np.sqrt(sum((wide[c].astype(np.float64) - plain[c]) ** 2 for c in ("x", "y", "z")))
        inside = wide["u"] < 160
        ratio = wide["sigma"] / plain["sigma"]
        assert inside.sum() > 500 and (~inside).sum() > 500
        # (a hair over 2 with three rays: the projector's floor, which no tile widens, reweighs a little)
        assert np.all((ratio[inside] > 1.5) & (ratio[inside] < 2.01)) and np.median(ratio[inside]) > 1.95, rays
        assert np.allclose(ratio[~inside], 1.0, rtol=1e-5), rays
        assert np.max(moved / plain["sigma"]) < 0.25 and np.all(moved[~inside] < 1e-4), rays


def test_a_projector_that_misses_the_cameras_points_is_discounted(tmp_path, monkeypatch, caplog):
    """The projector's calibration off (its light frame moved by half a projector pixel: every point half a
    pixel off, as much along camera 1's rays through it, where a camera-projector check sees nothing) and the
    cameras' right. Weighted by its decode's sigmas alone the projector's ray would pull every point off; its
    misses from the two cameras' points (report.json stereo.projector_check) give it a floor, and the three
    rays' points are as good as the cameras' alone, their sigmas honest. On the true rig nothing changes."""
    from ringscan.pipeline.reconstruct import view as view_module
    from tests.support.two_camera_scan import simulate_decoded_two_camera_scan

    scan = simulate_decoded_two_camera_scan(tmp_path / "exact", integer=False)
    li = scan.rig.light  # the paper's parallel light
    shift = li.pixel_pitch_mm * np.array([0.4, 0.3, 0.0])
    bad = dataclasses.replace(scan, rig=dataclasses.replace(scan.rig, light=dataclasses.replace(li, t=li.t + shift)))

    def run(s, rays, out):
        rep = reconstruct_scan(s, tmp_path / out, settings=_rays(rays), progress=False)
        return rep["views"][0], evaluate_recon(tmp_path / out, scan)["all"]

    v, good = run(scan, "all", "good")
    assert not v["stereo"]["projector_check"]["floor_applied"], v["stereo"]["projector_check"]
    _, cc = run(bad, "camera-camera", "cc")
    with caplog.at_level("WARNING"):
        v, fixed = run(bad, "all", "fixed")
    chk = v["stereo"]["projector_check"]
    assert chk["floor_applied"] and 0.2 < chk["floor_px"] < 2.0, chk
    # (the floor is isotropic and the ray keeps a little weight: within half again of the cameras alone; these
    # maps' sigmas are over-predicted by construction, so only the upper bounds of honesty are asked)
    assert fixed["median_mm"] < 1.5 * cc["median_mm"], (fixed["median_mm"], cc["median_mm"])
    assert fixed["sigma"]["median_ratio"] < 1.2 and fixed["sigma"]["beyond_3"] <= 0.05, fixed["sigma"]
    assert "the projector's calibration" not in caplog.text  # half a pixel: discounted, under the warning's 1 px
    # auto: camera 1's samples camera 2 does not see are camera-projector points, off by the miss: their
    # sigmas take it along the ray
    _, auto = run(bad, "auto", "auto")
    assert auto["sigma"]["beyond_3"] <= 0.05, auto["sigma"]
    worse = dataclasses.replace(scan, rig=dataclasses.replace(scan.rig, light=dataclasses.replace(
        li, t=li.t + 8 * shift)))  # four pixels off: said, and its points kept (inconsistent beyond 5 floors)
    with caplog.at_level("WARNING"):
        v, kept = run(worse, "all", "worse")
    assert "the projector's calibration" in caplog.text
    assert v["points"] > 0.95 * v["stereo"]["matches"], (v["points"], v["stereo"]["matches"])
    assert kept["median_mm"] < 1.5 * cc["median_mm"], (kept["median_mm"], cc["median_mm"])
    monkeypatch.setattr(view_module, "PROJECTOR_FLOOR_CHI2", np.inf)  # no floor: the projector's ray followed
    _, followed = run(bad, "all", "followed")
    # the points follow the projector; what their own rays' disagreement says of it (their chi) widens their
    # sigmas to the miss (kernels.stereo_rays.widen_by_chi), and only the floor brings the points back
    assert followed["median_mm"] > 5 * fixed["median_mm"], followed
    assert followed["sigma"]["median_sigma_mm"] > 3 * fixed["sigma"]["median_sigma_mm"], followed["sigma"]
    assert followed["sigma"]["beyond_3"] <= 0.05, followed["sigma"]
    _, auto_followed = run(bad, "auto", "auto_followed")
    assert auto_followed["median_mm"] > 5 * fixed["median_mm"], auto_followed
    assert good["median_mm"] < cc["median_mm"]  # (a true projector's ray helps)
