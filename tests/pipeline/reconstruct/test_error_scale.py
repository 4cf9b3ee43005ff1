"""The error model fitted from the two depths' disagreement recovers terms planted
in synthetic pairs (known truth), and leaves a model that is already right alone."""

from pathlib import Path

import numpy as np
import pytest

from ringscan.pipeline.reconstruct.error_scale import (MIN_PAIRS, apply_error_model, fit_error_model, fit_match_model,
                                                      sample_subset)


def _pairs(rng, n, *, k_rho=1.0, k_tan=1.0, f_rho=0.0, f_tan=0.0, miss_px=0.0):
    """n pairs drawn from the model: (args of fit_error_model), with a smooth miss
    across the epipolar line of amplitude ``miss_px`` over the camera image."""
    uv = rng.uniform(0, [640, 512], size=(n, 2))
    sigma_rho_px = rng.lognormal(np.log(0.02), 0.5, n)     # the decode's model, projector px
    sigma_tan_px = rng.lognormal(np.log(0.08), 0.5, n)
    d_rho = rng.lognormal(np.log(0.4), 0.8, n)             # depth per projector px, mm (geometry)
    d_tan = rng.lognormal(np.log(0.4), 0.8, n)
    s_rho, s_tan = sigma_rho_px * d_rho, sigma_tan_px * d_tan
    resid_var = rng.lognormal(np.log(0.003), 0.5, n)      # across the epipolar line, px^2
    gain = np.sqrt((s_rho ** 2 + s_tan ** 2) / resid_var)
    e_rho = rng.normal(0, np.sqrt((k_rho * s_rho) ** 2 + (f_rho * d_rho) ** 2))
    e_tan = rng.normal(0, np.sqrt((k_tan * s_tan) ** 2 + (f_tan * d_tan) ** 2))
    miss = miss_px * np.sin(uv[:, 0] / 150.0) * np.cos(uv[:, 1] / 170.0)  # smooth over 32 px tiles
    depth = 400.0
    depth_rho = depth + e_rho + gain * miss / 2
    depth_tan = depth + e_tan - gain * miss / 2
    return (depth_rho, s_rho, depth_tan, s_tan, sigma_rho_px, sigma_tan_px, resid_var, uv), miss


def test_a_model_that_is_right_is_left_alone():
    rng = np.random.default_rng(1)
    args, _ = _pairs(rng, 30000)
    fit = fit_error_model(*args)
    # 30k pairs fix a variance to ~1 %, five of them together to a few: the widened
    # sigmas stay within 5 % of the model's
    for px, k, f in ((args[4], fit["k_rho"], fit["floor_rho_px"]), (args[5], fit["k_tan"], fit["floor_tan_px"])):
        assert np.median(apply_error_model(px, k, f) / px) < 1.05
    assert fit["floor_px"] == 0.0
    assert 0.6 < fit["z_median"] < 0.75 and fit["pairs"] == 30000  # a Gaussian's median |z| is 0.674


def test_planted_terms_are_recovered():
    rng = np.random.default_rng(2)
    args, miss = _pairs(rng, 40000, k_rho=1.6, k_tan=1.3, f_rho=0.03, f_tan=0.12, miss_px=0.3)
    fit = fit_error_model(*args)
    assert fit["k_rho"] == pytest.approx(1.6, rel=0.1)
    assert fit["k_tan"] == pytest.approx(1.3, rel=0.1)
    # floors are smaller parts of each variance than the factors: 25 %
    assert fit["floor_rho_px"] == pytest.approx(0.03, rel=0.25)
    assert fit["floor_tan_px"] == pytest.approx(0.12, rel=0.25)
    # the smooth miss's RMS, read from 32 px tile medians (their own noise removed): 15 %
    assert fit["floor_px"] == pytest.approx(np.sqrt(np.mean(miss ** 2)), rel=0.15)
    # before the fit the pairs disagreed far beyond their sigmas; after it, as a t of 5 would
    assert fit["z_median"] > 1.0 and fit["beyond_3"] > 0.05
    assert 0.6 < fit["z_median_fitted"] < 0.85 and fit["beyond_3_fitted"] < 0.03


def test_indirect_light_terms_are_recovered_where_it_acts_and_stay_off_where_it_does_not():
    """A part of the view lit by bounced light (an indirect share g up to 0.5 above the view's on
    ~a third of the pairs) errs by a further b * g projector px per coordinate: the fit finds b;
    pairs whose errors do not grow with g (the same g, no such error) leave b near 0."""
    rng = np.random.default_rng(5)
    n = 40000
    args, _ = _pairs(rng, n)
    dr, s_rho, dt, s_tan, p_rho, p_tan, rv, uv = args
    g = np.where(rng.uniform(size=n) < 0.35, rng.uniform(0, 0.5, n), 0.0)
    plain = fit_error_model(*args, indirect=g)
    assert plain["indirect_rho_px"] < 0.02 and plain["indirect_tan_px"] < 0.02  # nothing to find
    b_rho, b_tan = 0.3, 0.6
    lit = (dr + rng.normal(0, b_rho * g * s_rho / p_rho), s_rho, dt + rng.normal(0, b_tan * g * s_tan / p_tan),
           s_tan, p_rho, p_tan, rv, uv)
    fit = fit_error_model(*lit, indirect=g)
    # ~14k pairs carry the terms, each a part of their variance: 25 %
    assert fit["indirect_rho_px"] == pytest.approx(b_rho, rel=0.25)
    assert fit["indirect_tan_px"] == pytest.approx(b_tan, rel=0.25)
    # the widened sigmas of the lit pairs hold against their planted ones (within 10 %)
    idx = g > 0.2
    sig = apply_error_model(p_rho, fit["k_rho"], fit["floor_rho_px"], indirect_px=fit["indirect_rho_px"], indirect=g)
    planted = np.sqrt(p_rho ** 2 + (b_rho * g) ** 2)
    assert np.median(sig[idx] / planted[idx]) == pytest.approx(1.0, abs=0.1)
    blind = fit_error_model(*lit)  # without g: the view's one model, fitted mostly where no light bounced
    assert blind["indirect_rho_px"] == 0.0 and blind["beyond_3_fitted"] > fit["beyond_3_fitted"]


def test_the_shading_term_is_recovered_and_widens_both_coordinates_alike():
    """Where the light changes fast across the image (a gradient g of its log, per camera px: a shading
    edge, a highlight, a silhouette) the camera's blur moves the sample's place by ~a g camera px in a
    direction of its own: each coordinate errs by a g projector px (the rig's ~1 projector px a camera px)
    along its own normal, independently. The fit finds a, the one magnitude both coordinates take;
    pairs whose errors do not grow with g leave it near 0, and without g nothing is fitted."""
    rng = np.random.default_rng(6)
    n = 40000
    args, _ = _pairs(rng, n)
    dr, s_rho, dt, s_tan, p_rho, p_tan, rv, uv = args
    g = np.where(rng.uniform(size=n) < 0.3, rng.lognormal(np.log(0.1), 1.0, n), rng.uniform(0, 0.02, n))
    plain = fit_error_model(*args, shading=g)
    assert plain["shading_rho_px"] < 0.02 and plain["shading_tan_px"] == plain["shading_rho_px"]
    a = 0.5
    steep = (dr + rng.normal(0, a * g * s_rho / p_rho), s_rho, dt + rng.normal(0, a * g * s_tan / p_tan), s_tan,
             p_rho, p_tan, rv, uv)
    fit = fit_error_model(*steep, shading=g)
    # ~12k pairs carry the term, each a part of their variance: 20 %
    assert fit["shading_rho_px"] == pytest.approx(a, rel=0.2) and fit["shading_tan_px"] == fit["shading_rho_px"]
    idx = g > 0.3
    sig = apply_error_model(p_tan, fit["k_tan"], fit["floor_tan_px"], shading_px=fit["shading_tan_px"], shading=g)
    planted = np.sqrt(p_tan ** 2 + (a * g) ** 2)
    assert np.median(sig[idx] / planted[idx]) == pytest.approx(1.0, abs=0.1)
    blind = fit_error_model(*steep)
    assert blind["shading_rho_px"] == 0.0 and blind["beyond_3_fitted"] > fit["beyond_3_fitted"]


def test_terms_that_act_on_few_pairs_do_not_stall_the_fit():
    """An indirect share that is a trace on most pairs (1e-5, the median of a view lit straight) and
    large on a few (5 %): each column of the fit is scaled by its median over the pairs where it acts.
    Scaled by its median over all pairs (~1e-10 of the other terms' units) L-BFGS-B stopped far from the
    likelihood's best (on a sphere in noise k_rho 4.6 where truth and the best both said ~3, and the
    default weighed rho too little: worse than rings alone); the planted factors come back to 10 %."""
    rng = np.random.default_rng(9)
    n = 40000
    args, _ = _pairs(rng, n, k_rho=3.0, k_tan=3.0)
    dr, s_rho, dt, s_tan, p_rho, p_tan, rv, uv = args
    g = np.where(rng.uniform(size=n) < 0.6, rng.lognormal(np.log(1e-5), 1.0, n), 0.0)
    few = rng.uniform(size=n) < 0.05
    g[few] = rng.uniform(0.05, 0.2, few.sum())
    b_tan = 1.0
    lit = (dr, s_rho, dt + rng.normal(0, b_tan * g * s_tan / p_tan), s_tan, p_rho, p_tan, rv, uv)
    fit = fit_error_model(*lit, indirect=g)
    assert fit["k_rho"] == pytest.approx(3.0, rel=0.1) and fit["k_tan"] == pytest.approx(3.0, rel=0.1)
    assert 0.6 < fit["z_median_fitted"] < 0.85


def test_too_few_pairs_change_nothing():
    rng = np.random.default_rng(3)
    args, _ = _pairs(rng, MIN_PAIRS - 1, k_rho=3.0)
    fit = fit_error_model(*args)
    assert (fit["k_rho"], fit["k_tan"], fit["floor_rho_px"], fit["floor_tan_px"], fit["floor_px"]) == (1, 1, 0, 0, 0)
    assert fit["pairs"] == MIN_PAIRS - 1


def test_pairs_without_both_depths_are_left_out():
    rng = np.random.default_rng(4)
    args, _ = _pairs(rng, 2000)
    dr = args[0].copy()
    dr[::2] = np.nan
    fit = fit_error_model(dr, *args[1:])
    assert fit["pairs"] == 1000


def test_apply_and_subset():
    s = apply_error_model(np.array([0.03, 0.0]), 2.0, 0.04)
    assert s.dtype == np.float32 and np.allclose(s, [0.072111, 0.04], rtol=1e-5)  # sqrt(0.06^2 + 0.04^2)
    idx = sample_subset(10, 4)
    assert idx.tolist() == [0, 3, 6, 9]
    assert sample_subset(3, 4).tolist() == [0, 1, 2]


@pytest.fixture(scope="module")
def uncalibrated_scan(tmp_path_factory):
    """A scan whose frames carry what the decode's noise model does not know: a
    projector of gamma 2.2 that scan.json says nothing of, with sharp (unblurred)
    pixels, and camera noise of 4 grey levels (the model assumes 1)."""
    import dataclasses
    import json

    from ringscan.pipeline.formats.patterns import parse_patterns
    from ringscan.pipeline.formats.scan import load_scan
    from ringscan.pipeline.simulate.scan import simulate_scan
    from ringscan.pipeline.simulate.virtual_rig import RenderSettings
    from tests.support.reconstruct_rig import PROJ, small_rig

    rig = small_rig()
    cam = dataclasses.replace(rig.camera, width=480, height=384,
                              K=np.array([[975.0, 0, 239.5], [0, 975.0, 191.5], [0, 0, 1]]))
    rig = dataclasses.replace(rig, camera=cam, light=dataclasses.replace(rig.light, gamma=2.2))
    spec = parse_patterns({"codec": "gray-rings", **PROJ, "rho0": 8.0, "pitch": 8.0, "bits": 6, "sector_bits": 6,
                           "angle_steps": 4, "angle_period": 12.0})
    folder = tmp_path_factory.mktemp("uncalibrated") / "scan"
    simulate_scan(folder, scene="sphere", rig=rig, patterns=spec, progress=False,
                  settings=RenderSettings(defocus_px=0.0, noise=4.0))
    d = json.loads((folder / "scan.json").read_text())
    d["rig"]["light"].pop("response", None)
    (folder / "scan.json").write_text(json.dumps(d))
    scan = load_scan(folder)
    assert scan.rig.light.gamma == 1.0
    return scan


def test_sigmas_hold_on_frames_the_model_does_not_know(uncalibrated_scan, tmp_path):
    from ringscan.kernels.triangulation import TriangulateSettings
    from ringscan.pipeline.evaluate.metrics import evaluate_recon
    from ringscan.pipeline.reconstruct.scan import reconstruct_scan
    from ringscan.pipeline.reconstruct.settings import ReconstructSettings

    figures = {}
    for c in ("rings", "both"):
        rep = reconstruct_scan(uncalibrated_scan, tmp_path / c, progress=False,
                               settings=ReconstructSettings(triangulate=TriangulateSettings(constraint=c)))
        figures[c] = (rep["views"][0], evaluate_recon(tmp_path / c, uncalibrated_scan)["all"])
    view, ev = figures["both"]
    model = view["calibration"]["error_model"]
    # the decode's own model was over-confident here (a Gaussian's median |z| is 0.67)...
    assert model["z_median"] > 1.0 and model["beyond_3"] > 0.05
    assert model["k_rho"] > 1.5 and model["k_tan"] > 1.5  # noise 4 where 1 is assumed
    # ...the fitted one holds against the truth: the bounds (a Gaussian: 0.67, 0.3 %)
    for c in ("rings", "both"):
        s = figures[c][1]["sigma"]
        assert 0.4 <= s["median_ratio"] <= 1.2 and s["beyond_3"] <= 0.05, (c, s)
    # and the default is no worse than rings alone (2 %: a median's spread over ~20k points)
    assert ev["median_mm"] <= 1.02 * figures["rings"][1]["median_mm"]


def test_rings_only_sigmas_hold_on_frames_the_model_does_not_know(uncalibrated_scan):
    """The same frames decoded without the angle (a codec without one): the ring's
    neighbours measure its errors; sigma then holds against the truth."""
    import dataclasses

    from ringscan.pipeline.evaluate.metrics import evaluate_view
    from ringscan.pipeline.reconstruct.view import reconstruct_view

    scan = dataclasses.replace(uncalibrated_scan,
                               patterns=dataclasses.replace(uncalibrated_scan.patterns, angle_steps=0))
    view = scan.views[0]
    cloud = reconstruct_view(scan, view)
    model = cloud.stats["error_model"]
    assert model["measured_by"] == "neighbours"
    assert model["z_median"] > 1.0 and model["k_rho"] > 1.5  # noise 4 grey levels where 1 is assumed
    s = evaluate_view(scan, view.name, cloud.points, sigma=cloud.sigma)["sigma"]
    # the bounds (2.1 % beyond 3 sigma before the samples no check along their ring reaches
    # got factors of their own, error_model.reach: 1.7 % with them; 6.5 % before the wider checks)
    assert model["reach"] and max(f for _, f, _ in model["reach"]) > 1.0
    assert 0.4 <= s["median_ratio"] <= 1.2 and s["beyond_3"] <= 0.05, s


def test_a_part_of_the_view_that_errs_more_gets_its_own_scale():
    """An object's pairs (here a 128x128 px corner of the view, ~5 % of the pairs)
    disagree 2x more than the rest: the view's model, fitted on all, fits the rest; the
    object's tiles get a variance factor of ~4, the rest none."""
    from ringscan.pipeline.reconstruct.error_scale import region_scale

    rng = np.random.default_rng(11)
    args, _ = _pairs(rng, 40000)
    dr, s_rho, dt, s_tan, px_rho, px_tan, rv, uv = args
    obj = (uv[:, 0] < 128) & (uv[:, 1] < 128)
    dr = np.where(obj, 400.0 + 2.0 * (dr - 400.0), dr)
    dt = np.where(obj, 400.0 + 2.0 * (dt - 400.0), dt)
    fit = fit_error_model(dr, s_rho, dt, s_tan, px_rho, px_tan, rv, uv)
    m = region_scale(fit["regions"], uv)
    # ~125 pairs a 32 px tile fix a variance to ~20 %; the median over the object's 16 tiles to 25 %
    assert np.median(m[obj]) == pytest.approx(4.0, rel=0.25)
    assert np.median(m[~obj]) == 1.0 and np.mean(m[~obj] > 1.3) < 0.02
    z = np.abs(dr - dt) / np.sqrt((s_rho ** 2 + s_tan ** 2) * m)
    assert 0.6 < np.median(z[obj]) < 0.8  # the object's pairs as a Gaussian's (0.674)


def test_rho_measured_by_its_neighbours_leaves_the_pairs_the_angles_terms():
    """A dense code's two predicted errors both scale with the pixel's contrast: the pairs alone
    cannot tell whose error they disagree by. Planted: rho as predicted, the angle 4x worse. Given
    rho's terms (its neighbours measure them), the pairs fit the angle's: k_tan ~4."""
    rng = np.random.default_rng(21)
    n = 30000
    args, _ = _pairs(rng, n)
    dr, s_rho, dt, s_tan, p_rho, p_tan, rv, uv = args
    s_tan = 3.0 * s_rho  # collinear: one contrast drives both
    p_tan = s_tan / (s_rho / p_rho)
    depth = 400.0
    dr = depth + rng.normal(0, s_rho)
    dt = depth + rng.normal(0, 4.0 * s_tan)
    fit = fit_error_model(dr, s_rho, dt, s_tan, p_rho, p_tan, rv, uv, rho_terms=(1.0, 0.0))
    assert fit["k_rho"] == 1.0 and fit["floor_rho_px"] == 0.0  # held as given
    assert fit["k_tan"] == pytest.approx(4.0, rel=0.1)  # 30k pairs: ~1 % on a variance
    blind = fit_error_model(dr, s_rho, dt, s_tan, p_rho, p_tan, rv, uv)
    assert blind["k_rho"] > 2.0  # the pairs alone put much of it on rho (8.3 and 2.9 measured)


def test_tile_factors_all_at_once_are_each_tiles_own():
    """_t_scales (the tiles' factors in one pass) against _t_scale of each tile: the same fixed points to
    rounding (its means summed in order rather than pairwise), over tiles of 20-600 pairs."""
    from ringscan.pipeline.reconstruct.error_scale import _t_scale, _t_scales

    rng = np.random.default_rng(3)
    counts = rng.integers(20, 600, 300)
    starts = np.r_[0, np.cumsum(counts)[:-1]]
    u = (rng.standard_t(5, counts.sum()) * rng.uniform(0.5, 3, counts.sum())) ** 2
    one = np.array([_t_scale(u[a:a + c]) for a, c in zip(starts, counts)])
    np.testing.assert_allclose(_t_scales(u, starts, counts), one, rtol=1e-12)
    assert np.ptp(one) > 1.0  # the tiles' factors differ: a test of each tile's own
    assert _t_scales(u, starts[:0], counts[:0]).size == 0


# ----------------------------------------------------------------------------- the fit's solver (NumPy only)


def test_the_box_solver_finds_a_quadratics_corner():
    """f = (x - 3)^2 + (y + 1)^2 + (z - 0.5)^2 in [0, 2] x [0, 5] x [0.5, 0.5]: (2, 0, 0.5), the third fixed."""
    from ringscan.pipeline.reconstruct.error_scale import minimize_in_box

    t = np.array([3.0, -1.0, 0.5])
    x = minimize_in_box(lambda x: float(np.sum((x - t) ** 2)), lambda x: (2 * (x - t), 2 * np.eye(3)),
                        np.array([1.0, 1.0, 0.5]), np.array([0.0, 0.0, 0.5]), np.array([2.0, 5.0, 0.5]))
    assert np.array_equal(x, [2.0, 0.0, 0.5])


@pytest.mark.parametrize("seed", range(6))
def test_the_variance_fit_reaches_scipys_optimum(seed):
    """The variance model's Student-t fit (``_fit_variances``, NumPy's projected Newton steps) against SciPy's
    L-BFGS-B (its solver before) on the same likelihood: random terms, some near zero (at their bound), one
    fixed by equal bounds, one with an upper bound: the likelihood no worse than L-BFGS-B's to 1e-12 and the
    variances the same to 1e-4 of the largest (L-BFGS-B stops at ftol 1e-12)."""
    from scipy.optimize import minimize

    import ringscan.pipeline.reconstruct.error_scale as es

    rng = np.random.default_rng(seed)
    n, m = 20000, 5
    X = rng.uniform(0, 1, (n, m)) ** 3  # each term's variance per unit, uneven
    X[rng.random((n, m)) < 0.6] = 0.0  # terms that act on some pairs only
    X[:, 0] += 0.05  # (every pair has some variance)
    P = np.array([1.0, 0.5, 0.0, 2.0, 0.3]) * rng.uniform(0.5, 2.0, m)
    d2 = (X @ P) * rng.standard_t(5, n) ** 2 / 1.2
    lower = np.array([1.0, 0.0, 0.0, 0.0, 0.0])
    upper = np.array([np.inf, np.inf, np.inf, 1.5, 0.3])
    upper[4] = lower[4] = 0.3  # fixed
    got = es._fit_variances(X, d2, lower, upper)

    col = np.mean(X, axis=0)
    scale = float(np.median(d2))
    Xs, d2s = X / col, d2 / scale

    def nll(q):
        var = np.maximum(es.T_SCALE ** 2 * (Xs @ q), 1e-300)
        u = d2s / (es.T_DOF * var)
        g = 0.5 / var - 0.5 * (es.T_DOF + 1) * u / (var * (1 + u))
        return (0.5 * np.sum(np.log(var)) + 0.5 * (es.T_DOF + 1) * np.sum(np.log1p(u))) / n, \
            es.T_SCALE ** 2 * (Xs.T @ g) / n

    lo, hi = lower * col / scale, upper * col / scale
    bounds = [(a, b if np.isfinite(b) else None) for a, b in zip(lo, hi)]
    start = np.where(np.isfinite(hi), 0.5 * (lo + hi), lo + 0.2)
    ref = minimize(nll, start, jac=True, method="L-BFGS-B", bounds=bounds,
                   options={"maxiter": 1000, "ftol": 1e-12, "gtol": 1e-9})
    want = np.maximum(ref.x, lo) * scale / col
    assert nll(got * col / scale)[0] <= ref.fun + 1e-12
    assert np.max(np.abs(got - want)) <= 1e-4 * np.max(np.abs(want)), (got, want)
    assert abs(got[4] - 0.3) < 1e-12 and got[3] <= 1.5 * (1 + 1e-12) and (got >= lower).all()  # (units and back)


def test_a_default_reconstruct_loads_no_scipy(tmp_path):
    """The view's error model fits with NumPy alone: a ``ringscan reconstruct`` of a scan with the angle code
    (the default patterns) imports no SciPy (its optimisers cost a process ~0.3 s, a fifth of a one-view run),
    nor, with one camera, the two-camera modules."""
    import subprocess
    import sys

    from tests.support.reconstruct_rig import PROJ, small_rig

    probe = (
        "import sys\n"
        "from ringscan.pipeline.formats.patterns import parse_patterns\n"
        "from ringscan.pipeline.simulate.scan import simulate_scan\n"
        "from ringscan.pipeline.reconstruct.scan import reconstruct_scan\n"
        "from tests.support.reconstruct_rig import PROJ, small_rig\n"
        f"folder = {str(tmp_path / 'scan')!r}\n"
        "spec = parse_patterns({'codec': 'gray-rings', **PROJ, 'rho0': 8.0, 'pitch': 8.0, 'bits': 6,\n"
        "                       'sector_bits': 6, 'angle_steps': 4, 'angle_period': 12.0})\n"
        "simulate_scan(folder, scene='sphere', rig=small_rig(), patterns=spec, progress=False)\n"
        f"rep = reconstruct_scan(folder, {str(tmp_path / 'rec')!r}, progress=False)\n"
        "print('FIT', 'error_model' in rep['views'][0]['calibration'])\n"
        "print('SCIPY', any(m == 'scipy' or m.startswith('scipy.') for m in sys.modules))\n"
        "print('STEREO', any(m.startswith(('ringscan.kernels.stereo', 'ringscan.pipeline.reconstruct.stereo'))\n"
        "                    for m in sys.modules))\n"
    )
    del PROJ, small_rig  # (imported above only to fail here, not in the probe, if the helper moves)
    r = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, timeout=600,
                       cwd=Path(__file__).resolve().parents[3])
    assert r.returncode == 0, r.stderr[-2000:]
    assert "FIT True" in r.stdout and "SCIPY False" in r.stdout, r.stdout
    assert "STEREO False" in r.stdout  # (one camera: the matcher's and the rays' modules stay unloaded, ~75 ms)


def _matches(rng, n, *, k=1.0, f=0.0, miss_px=0.0):
    """n matches' epipolar distances drawn from the two-camera model (args of fit_match_model): camera 1's and
    camera 2's predicted sigmas, the line's slope g^2, and a smooth miss of amplitude ``miss_px``."""
    uv = rng.uniform(0, [640, 512], size=(n, 2))
    s1 = rng.lognormal(np.log(0.02), 0.5, n)
    s2 = rng.lognormal(np.log(0.012), 0.5, n)
    g2 = rng.lognormal(np.log(1.0), 0.3, n)
    var = k * k * (s2 * s2 + g2 * s1 * s1) + f * f * (1 + g2)
    # a rig's miss across the lines: an offset that drifts over the image (a camera turned a little)
    miss = miss_px * (1.0 + 0.3 * (uv[:, 0] - 320) / 320 - 0.2 * ((uv[:, 1] - 256) / 256) ** 2)
    return rng.normal(0.0, np.sqrt(var)) + miss, g2, s1, s2, uv, miss


@pytest.mark.parametrize("k, f", [(1.0, 0.0), (1.8, 0.0), (1.0, 0.03), (1.5, 0.02)])
def test_the_match_model_recovers_a_planted_factor_and_floor_past_a_calibrations_miss(k, f):
    """Planted k and floor come back (40k matches fix them to a few %; a model that is already right fits
    k 1 and a floor far below the sigmas), and a smooth miss of ~0.5 px across the lines (a rig off by more
    than ten sigmas) is left out of both: it is reported as ``miss_px``, not taken for the decode's error."""
    rng = np.random.default_rng(int(k * 100 + f * 1000))
    d, g2, s1, s2, uv, miss = _matches(rng, 40000, k=k, f=f, miss_px=0.5)
    m = fit_match_model(d, g2, s1, s2, uv)
    assert m["pairs"] == 40000
    assert abs(m["k"] - k) < 0.05 * k
    # the floor to a few thousandths px: what is left of the miss's drift within a 32 px tile (~0.004 px
    # RMS here) reads as floor; it widens the sigmas the planted model gives by < 5 %
    assert abs(m["floor_px"] - f) < 0.007
    v = s2 * s2 + g2 * s1 * s1
    planted = np.sqrt(k * k * v + f * f * (1 + g2))
    fitted = np.sqrt(m["k"] ** 2 * v + m["floor_px"] ** 2 * (1 + g2))
    assert 0.97 < np.median(fitted / planted) < 1.05
    assert abs(m["miss_px"] / np.sqrt(np.mean(miss ** 2)) - 1) < 0.05
    assert 0.6 < m["z_median_fitted"] < 0.75 and m["beyond_3_fitted"] < 0.01
    assert m["z_median"] > 3.0  # as predicted, the miss dominates


def test_the_match_model_without_a_floor_fits_one_factor_and_needs_enough_matches():
    rng = np.random.default_rng(4)
    d, g2, s1, s2, uv, _ = _matches(rng, 20000, k=1.0, f=0.03)
    m = fit_match_model(d, g2, s1, s2, uv, floor=False)
    assert m["floor_px"] == 0.0 and m["k"] > 1.5  # the floor's share taken by the one factor
    assert 0.55 < m["z_median_fitted"] < 0.8
    few = fit_match_model(d[:MIN_PAIRS - 1], g2[:MIN_PAIRS - 1], s1[:MIN_PAIRS - 1], s2[:MIN_PAIRS - 1],
                          uv[:MIN_PAIRS - 1])
    assert few == {}


def test_the_match_model_widens_the_tiles_whose_matches_disagree_more():
    """Matches in one 64 x 64 px corner of camera 1 err 3 times their predicted sigmas (a grazing silhouette, a
    shadow edge), the rest as predicted: the view's k stays near 1, the corner's tiles get a variance factor
    near 9 (``regions``, as a one-camera model has them), none of the rest more than a little, and the
    fitted distances hold: beyond 3 sigma the corner's 30 % falls to a few %."""
    from ringscan.pipeline.reconstruct.error_scale import region_scale

    rng = np.random.default_rng(12)
    d, g2, s1, s2, uv, _ = _matches(rng, 40000)
    corner = (uv[:, 0] < 64) & (uv[:, 1] < 64)
    d = np.where(corner, 3.0 * d, d)
    m = fit_match_model(d, g2, s1, s2, uv)
    assert m["k"] < 1.1 and m["regions"]["tile_px"] == 32
    scale = region_scale(m["regions"], uv)
    assert 6.0 < np.median(scale[corner]) < 12.0 and np.quantile(scale[~corner], 0.99) < 1.5
    z = np.abs(d) / np.sqrt((m["k"] ** 2 * (s2 * s2 + g2 * s1 * s1) + m["floor_px"] ** 2 * (1 + g2)) * scale)
    assert np.mean(np.abs(d[corner]) / np.sqrt(s2[corner] ** 2 + g2[corner] * s1[corner] ** 2) > 3) > 0.25
    assert np.mean(z[corner] > 3) < 0.05 and m["beyond_3_fitted"] < 0.01


def test_the_match_model_leaves_out_mismatches_the_triangulation_drops():
    """2 % of the matches 5-30 px off their lines (camera 2's code found on another surface: the two rays'
    residual drops them as inconsistent) pull the fit wider; beyond ``max_distance_px`` they are not fitted."""
    rng = np.random.default_rng(9)
    d, g2, s1, s2, uv, _ = _matches(rng, 20000, k=1.2, f=0.01)
    bad = rng.random(d.size) < 0.02
    d = np.where(bad, rng.uniform(5, 30, d.size) * np.sign(rng.normal(size=d.size)), d)
    kept = fit_match_model(d, g2, s1, s2, uv, max_distance_px=4.0)
    assert kept["pairs"] == int(np.count_nonzero(~bad))
    assert abs(kept["k"] - 1.2) < 0.06 and abs(kept["floor_px"] - 0.01) < 0.004
    every = fit_match_model(d, g2, s1, s2, uv)
    assert every["k"] > kept["k"] + 0.05  # (the Student-t holds them to ~8 % of k; left out, none)

