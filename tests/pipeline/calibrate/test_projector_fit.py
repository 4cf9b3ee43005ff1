"""fit_projector's distortion choices (auto / fit / hold), its residual correlation and depth checks, its
weights, and triangulation_covariance, against a known projector (pipeline/calibrate/projector_fit.py)."""

from __future__ import annotations

from dataclasses import replace

import cv2
import numpy as np
import pytest

from ringscan.pipeline.calibrate.projector_fit import ProjectorSettings, fit_projector, triangulation_covariance
from ringscan.pipeline.calibrate.rig_refine import relative_pose, rotation_angle_deg, triangulate_pair
from tests.support.stereo_truth import oblique_devices, project, surface_points

SIZE = (1280, 800)


def pairs(dist, *, n=3000, noise_px=0.1, seed=0, points=None):
    """World points on the wavy surface and the projector's pixels of them (Gaussian noise), the projector."""
    _, _, proj = oblique_devices()
    proj = replace(proj, dist=np.asarray(dist, float))
    X = surface_points(n, seed=seed) if points is None else points
    up, ok = project(proj, X)
    rng = np.random.default_rng(seed + 1)
    return X[ok], up[ok] + rng.normal(0, noise_px, (int(ok.sum()), 2)), proj


def decision(fit, term: str) -> str:
    return next(d for d in fit.decisions if d.startswith(term))


def test_auto_fits_the_tangential_distortion_a_lens_has():
    X, up, proj = pairs([-0.08, 0.0, 0.002, -0.001, 0.0])
    fit = fit_projector(X, up, size=SIZE)
    assert decision(fit, "p1, p2").startswith("p1, p2: fitted (auto")
    assert fit.light.dist[2] == pytest.approx(0.002, abs=4 * fit.std["p1"] + 1e-5)
    assert fit.light.dist[3] == pytest.approx(-0.001, abs=4 * fit.std["p2"] + 1e-5)
    assert abs(fit.light.K[1, 2] - proj.K[1, 2]) < 0.002 * SIZE[1]
    assert rotation_angle_deg(fit.light.R @ proj.R.T) < 0.02
    # held at 0 they move the principal point and the pose instead
    held = fit_projector(X, up, size=SIZE, settings=ProjectorSettings(tangential="hold"))
    assert "p1" in held.fixed and "p2" in held.fixed and held.light.dist[2] == 0.0
    assert abs(held.light.K[1, 2] - proj.K[1, 2]) > 5 * abs(fit.light.K[1, 2] - proj.K[1, 2])
    assert held.rms_px > 1.2 * fit.rms_px


def test_auto_holds_what_the_data_do_not_ask_for_and_fit_fits_it_anyway():
    X, up, proj = pairs([-0.08, 0.0, 0.0, 0.0, 0.0])
    fit = fit_projector(X, up, size=SIZE)
    assert {"k2", "p1", "p2", "k3"} <= set(fit.fixed) and "k1" not in fit.fixed
    assert decision(fit, "p1, p2").startswith("p1, p2: held at 0 (auto")
    assert decision(fit, "k2").startswith("k2: held at 0 (auto")
    assert fit.light.dist[0] == pytest.approx(-0.08, abs=0.005)
    forced = fit_projector(X, up, size=SIZE, settings=ProjectorSettings(radial="fit", tangential="fit"))
    assert not {"k2", "p1", "p2"} & set(forced.fixed)
    none = fit_projector(X, up, size=SIZE, settings=ProjectorSettings(radial="hold", tangential="hold"))
    assert set(none.fixed) == {"k1", "k2", "p1", "p2", "k3"} and not none.light.dist.any()


def test_independent_noise_gives_the_bound_correlated_errors_widen_it():
    X, up, _ = pairs([-0.08, 0.0, 0.0, 0.0, 0.0])
    fit = fit_projector(X, up, size=SIZE)
    assert 1.0 <= fit.correlation < 1.6
    assert fit.std["fx"] == pytest.approx(fit.std_noise["fx"] * fit.correlation ** 0.5, rel=1e-6)
    # a smooth error field over the projector image (as systematic decoding errors are): neighbours share it
    bumpy = up + 0.3 * np.stack([np.sin(up[:, 1] / 60.0), np.cos(up[:, 0] / 80.0)], 1)
    worse = fit_projector(X, bumpy, size=SIZE)
    assert worse.correlation > 5
    assert worse.std["position"] > 2 * worse.std_noise["position"]
    assert worse.report()["correlation"] == worse.correlation


def test_little_depth_along_the_projector_axis_is_noted():
    rng = np.random.default_rng(5)
    # a slab 20 mm deep, 1.8 m x 1.3 m wide, ~3.1 m from the projector: thick enough to fit, too flat to tell
    # the focal length from the distance
    X = np.stack([rng.uniform(-900, 900, 6000), rng.uniform(-50, 1250, 6000), rng.uniform(290, 310, 6000)], 1)
    X, up, _ = pairs([-0.08, 0.0, 0.0, 0.0, 0.0], points=X, noise_px=0.05)
    fit = fit_projector(X, up, size=SIZE, settings=ProjectorSettings(min_thickness=0.005))
    assert fit.depth_ratio < 0.01
    assert abs(fit.focal_distance_correlation) > 0.95
    assert any("focal length and the distance trade" in note for note in fit.notes)
    deep = fit_projector(*pairs([-0.08, 0.0, 0.0, 0.0, 0.0])[:2], size=SIZE)
    assert deep.depth_ratio > 0.1 and not any("trade" in note for note in deep.notes)


@pytest.mark.parametrize("field,value", [("tangential", "maybe"), ("radial", True), ("alpha", 0.7),
                                         ("correlation_cells", 0), ("min_depth_ratio", -1.0)])
def test_settings_refuse_bad_values(field, value):
    with pytest.raises(ValueError, match=field):
        ProjectorSettings(**{field: value})


def test_pairs_weighted_by_their_predicted_uncertainty_fit_better():
    X, up, proj = pairs([-0.08, 0.0, 0.0, 0.0, 0.0], noise_px=0.0)
    rng = np.random.default_rng(7)
    sigma = np.where(rng.random(len(X)) < 0.5, 0.05, 1.5)  # half the pairs 30x worse, and known to be
    noisy = up + rng.normal(0, 1, up.shape) * sigma[:, None]
    fixed = ProjectorSettings(radial="fit", tangential="hold")  # the choice is the other tests'
    plain = fit_projector(X, noisy, size=SIZE, settings=fixed)
    weighted = fit_projector(X, noisy, size=SIZE, settings=fixed, pixel_sigma=sigma)
    # independent noise: the weighted fit's bound is the better one, and so is its projector
    assert weighted.std_noise["position"] < 0.5 * plain.std_noise["position"]
    err = [np.linalg.norm(f.light.center - proj.center) for f in (plain, weighted)]
    assert err[1] < err[0] and err[1] < 3 * weighted.std["position"]
    assert weighted.weighted and not plain.weighted
    with pytest.raises(ValueError, match="pixel_sigma"):
        fit_projector(X, noisy, size=SIZE, settings=fixed, pixel_sigma=sigma[:10])


def test_triangulation_covariance_matches_the_scatter_of_noisy_triangulations():
    cam1, cam2, _ = oblique_devices()
    X = surface_points(3, seed=2)
    C = triangulation_covariance(cam1, cam2, X, np.full(3, 0.2), np.full(3, 0.2))
    R, t = relative_pose(cam1, cam2)
    rng = np.random.default_rng(3)
    for i in range(3):
        (u1, _), (u2, _) = project(cam1, X[i:i + 1]), project(cam2, X[i:i + 1])
        u1 = u1 + rng.normal(0, 0.2, (4000, 2))
        u2 = u2 + rng.normal(0, 0.2, (4000, 2))
        n1 = cv2.undistortPoints(u1.reshape(-1, 1, 2), cam1.K, cam1.dist).reshape(-1, 2)
        n2 = cv2.undistortPoints(u2.reshape(-1, 1, 2), cam2.K, cam2.dist).reshape(-1, 2)
        Xs = (triangulate_pair(R, t, n1, n2) - cam1.t) @ cam1.R
        emp = np.cov(Xs.T)
        # the long axis (depth) and the total spread within 15 % of the prediction
        assert np.trace(emp) == pytest.approx(np.trace(C[i]), rel=0.15)
        assert np.linalg.eigvalsh(emp)[-1] == pytest.approx(np.linalg.eigvalsh(C[i])[-1], rel=0.15)


def test_no_pinhole_projector_names_a_parallel_light():
    """Projector pixels that are an affine function of points in depth: a collimated light, said so; others
    (no camera model fits them): the projector's size and the scan's projector coordinates to check."""
    from ringscan.pipeline.calibrate.projector_fit import no_pinhole_projector

    rng = np.random.default_rng(1)
    X = rng.uniform(-100, 100, (500, 3))
    parallel = X[:, :2] * 2.0 + [640, 400]
    assert "parallel (collimated) light" in no_pinhole_projector(X, parallel)
    wild = rng.uniform(0, 1280, (500, 2))
    msg = no_pinhole_projector(X, wild)
    assert "parallel" not in msg and "check --projector WxH" in msg
