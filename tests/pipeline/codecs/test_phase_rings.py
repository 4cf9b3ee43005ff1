"""phase-rings end to end against the virtual rig's truth: reconstruct, response
handling, the issue's accuracy figures on the default rig."""

import dataclasses
import json
from dataclasses import dataclass, field

import numpy as np
import pytest
import warp as wp

from ringscan.kernels.settings import PhaseSettings
from ringscan.pipeline.codecs.phase_rings import PhaseRingsSettings, estimate_camera_gamma, extract_phase_rings
from ringscan.pipeline.evaluate.metrics import evaluate_view, truth_points
from ringscan.pipeline.formats.atomic import read_json
from ringscan.pipeline.formats.patterns import parse_patterns
from ringscan.pipeline.formats.ply import read_ply
from ringscan.pipeline.formats.scan import read_view_frames
from ringscan.pipeline.reconstruct.scan import reconstruct_scan
from ringscan.pipeline.reconstruct.settings import ReconstructSettings
from ringscan.pipeline.reconstruct.view import reconstruct_view
from ringscan.pipeline.simulate.scan import simulate_scan
from ringscan.pipeline.simulate.virtual_rig import RenderSettings
from ringscan.tools.bench.dense import bench_dense
from ringscan.tools.cli import main
from tests.support.crop_rig import PROJ, WINDOW, crop_rig
from tests.support.projector_window import seen_projector_pixels

PHASE = {"codec": "phase-rings", **PROJ, "rho0": 8.0, "pitch": 8.0, "bits": 6, "sector_bits": 6, "steps": 4}


@dataclass(frozen=True)
class _Settings(ReconstructSettings):
    """ReconstructSettings with a phase block (the phase-rings codec picks it: ``PhaseRingsCodec.settings_from``)."""

    phase: PhaseSettings = field(default_factory=PhaseSettings)


def lit_object_fraction(scan, view_name, u, v):
    """Of the pixels that see the object lit (truth, > 0.5 mm above the plane),
    the fraction that have a point."""
    X, pix = truth_points(scan, view_name)
    obj = pix[X[:, 2] > 0.5]
    w = scan.rig.camera.width
    have = np.zeros(scan.rig.camera.width * scan.rig.camera.height, bool)
    have[np.rint(v).astype(int) * w + np.rint(u).astype(int)] = True
    return float(have[obj].mean()), int(obj.size)


@pytest.fixture(scope="module")
def small_phase_scan(tmp_path_factory):
    return simulate_scan(tmp_path_factory.mktemp("phase") / "scan", scene="sphere", rig=crop_rig(),
                         patterns=parse_patterns(PHASE), progress=False)


def test_the_projector_window_holds_what_the_cameras_see(small_phase_scan):
    """The largest crop here sees projector pixels inside WINDOW only, 8 px from its edges at the least (the
    defocus blur's sigma is 0.7 px; a camera pixel's sub-samples ~1 px): its frames are the whole projector's
    (tests/test_support.py renders a window and the whole projector alike)."""
    assert small_phase_scan.rig.camera.width == 320 and small_phase_scan.rig.light.width == WINDOW[2]
    p = seen_projector_pixels(small_phase_scan)
    assert len(p) == 320 * 256  # every pixel sees the sphere or the plane
    assert (p >= 8).all() and (p[:, 0] <= WINDOW[2] - 1 - 8).all() and (p[:, 1] <= WINDOW[3] - 1 - 8).all(), \
        (p.min(0), p.max(0))


def test_reconstruct_phase_rings_truth(small_phase_scan, tmp_path):
    """A crop of the default rig looking at the sphere: a point at every lit pixel."""
    rep = reconstruct_scan(small_phase_scan, tmp_path / "rec", progress=False)
    v = rep["views"][0]
    assert rep["codec"] == "phase-rings"
    assert v["points"] > 75000 and v["points"] + sum(v["dropped"].values()) == v["samples"]
    assert v["samples"] <= v["pixels_decoded"]
    assert set(v["phase_dropped"]) == {"dark", "code", "modulation", "slip", "lonely"}
    assert v["camera_gamma"] == 2.2
    ply = read_ply(tmp_path / "rec" / "view_000.ply")
    assert np.all(ply["ring"] == -1)
    # one point per pixel, at pixel centres, in raster order
    assert np.all(ply["u"] == np.rint(ply["u"])) and np.all(ply["v"] == np.rint(ply["v"]))
    lin = ply["v"].astype(np.int64) * 320 + ply["u"].astype(np.int64)
    assert np.all(np.diff(lin) > 0)
    # rho is continuous, not a set of ring radii: every part of the period is there
    frac = np.mod((ply["rho"] - 8.0) / 8.0, 1.0)
    assert np.histogram(frac, bins=8, range=(0, 1))[0].min() > 0.08 * frac.size
    # the PLY's points against the truth (evaluate_recon's figures for the view, without reading the PLY again)
    res = evaluate_view(small_phase_scan, "view_000", np.stack([ply["x"], ply["y"], ply["z"]], -1), sigma=ply["sigma"])
    assert res["median_mm"] < 0.004 and res["p95_mm"] < 0.02, res
    assert res["frac_over_1mm"] <= 0.003, res
    frac, n = lit_object_fraction(small_phase_scan, "view_000", ply["u"], ply["v"])
    assert n > 75000 and frac > 0.97, frac


def test_cli_reconstructs_phase_rings(small_phase_scan, tmp_path, capsys):
    assert main(["reconstruct", str(small_phase_scan.folder), "--out", str(tmp_path / "r"), "--no-progress",
                 "--device", "cpu"]) == 0
    assert "points" in capsys.readouterr().out
    rep = read_json(tmp_path / "r" / "report.json")
    assert rep["codec"] == "phase-rings" and rep["views"][0]["points"] > 75000


def _view_median(scan, settings=ReconstructSettings()):
    """(median distance to the truth (mm), the view's figures as report.json has them) of the scan's view,
    reconstructed and evaluated in memory (reconstruct_scan's and evaluate_recon's view, without the PLY
    written and read back: test_reconstruct_phase_rings_truth and test_cli_reconstructs_phase_rings go
    through the files)."""
    cloud = reconstruct_view(scan, scan.views[0], settings=settings)
    return evaluate_view(scan, scan.views[0].name, cloud.points, sigma=cloud.sigma)["median_mm"], cloud.stats


def _median_error(scan, response):
    return _view_median(scan, _Settings(phase=PhaseSettings(response=response, smooth_radius=0)))


@pytest.fixture(scope="module")
def quiet_phase_scan(tmp_path_factory):
    """No sensor noise: what is left of the error is the response's phase error. The 160x128 crop
    (all sphere): the response's error is per pixel, the same on fewer pixels (measured there:
    linear / rig median 4.5, estimate / rig 1.00, estimated gamma 2.198)."""
    return simulate_scan(tmp_path_factory.mktemp("quiet") / "scan", scene="sphere", rig=crop_rig(width=160, height=128),
                         patterns=parse_patterns(PHASE), settings=RenderSettings(noise=0.0), progress=False)


def test_response_modes(quiet_phase_scan):
    rig_med, view = _median_error(quiet_phase_scan, "rig")
    lin_med, _ = _median_error(quiet_phase_scan, "linear")
    est_med, est_view = _median_error(quiet_phase_scan, "estimate")
    assert view["camera_gamma"] == 2.2
    assert lin_med > 2.5 * rig_med, (lin_med, rig_med)
    assert est_med < 1.05 * rig_med, (est_med, rig_med)
    assert abs(est_view["camera_gamma"] - 2.2) < 0.05


def light_rig(light_gamma):
    """:func:`crop_rig` at 240x192 (camera gamma 2.2) with a light of response ``light_gamma``.
    Measured medians, blind / linear light: 1.69 on the 320x256 crop, 1.56 on this one, 1.35 on
    160x128 (the central pixels see less of the sphere's slope), so 240x192 keeps a clear margin
    over the 1.3 asked; pre-compensated / linear stays within 1 % at every size."""
    rig = crop_rig(width=240, height=192)
    return dataclasses.replace(rig, light=dataclasses.replace(rig.light, gamma=light_gamma))


@pytest.fixture(scope="module")
def gamma_light_scans(tmp_path_factory):
    """The sphere on the 240x192 crop: under a linear light with plain frames (key "linear"), and under
    a light of gamma 2.2 with frames pre-compensated for it (patterns.precompensated_gamma 2.2) and plain frames."""
    d = tmp_path_factory.mktemp("lightgamma")
    scans = {pre: simulate_scan(d / f"pre{pre}", scene="sphere", rig=light_rig(2.2),
                                patterns=parse_patterns({**PHASE, "precompensated_gamma": pre} if pre != 1.0 else PHASE),
                                progress=False)
             for pre in (2.2, 1.0)}
    scans["linear"] = simulate_scan(d / "linear", scene="sphere", rig=light_rig(1.0), patterns=parse_patterns(PHASE),
                                    progress=False)
    return scans


def test_precompensated_frames_on_a_gamma_light(gamma_light_scans, caplog):
    """Virtual rig, light gamma 2.2: frames pre-compensated for it and decoded with the matching
    rig are as accurate as a linear light; plain frames decoded without the light's gamma are not."""
    linear_med, _ = _view_median(gamma_light_scans["linear"])  # light gamma 1, plain frames
    pre = gamma_light_scans[2.2]
    assert pre.patterns.precompensated_gamma == 2.2 and pre.rig.light.gamma == 2.2
    pre_med, pre_view = _view_median(pre)
    assert pre_view["light_gamma"] == 1.0 and pre_view["precompensated_gamma"] == 2.2  # nothing left to undo
    plain = gamma_light_scans[1.0]
    blind = dataclasses.replace(plain, rig=light_rig(1.0))  # a rig that does not know the light's gamma
    blind_med, blind_view = _view_median(blind)
    assert blind_view["light_gamma"] == 1.0
    undone_med, undone_view = _view_median(plain)  # plain frames, the rig's gamma undone
    assert undone_view["light_gamma"] == 2.2
    print(json.dumps({"linear_light": linear_med, "precompensated": pre_med, "plain_decoded_blind": blind_med,
                      "plain_gamma_undone_in_decoder": undone_med}))
    assert abs(pre_med / linear_med - 1.0) <= 0.05, (pre_med, linear_med)
    assert blind_med >= 1.3 * linear_med, (blind_med, linear_med)
    assert undone_med <= 1.1 * linear_med, (undone_med, linear_med)
    # pre-compensated frames decoded with a rig whose light is linear: the residual 1/2.2 is undone, with a warning
    with caplog.at_level("WARNING"):
        _, mis_view = _view_median(dataclasses.replace(pre, rig=light_rig(1.0)))
    assert mis_view["light_gamma"] == pytest.approx(1.0 / 2.2)
    assert "pre-compensated for a light gamma of 2.2" in caplog.text


def test_estimate_camera_gamma(small_phase_scan):
    spec = small_phase_scan.patterns
    fr = read_view_frames(small_phase_scan, small_phase_scan.views[0])
    kw = dict(bits=spec.bits, sector_bits=spec.sector_bits, steps=spec.steps)
    assert estimate_camera_gamma(fr, **kw) == pytest.approx(2.2, abs=0.1)
    # re-encode the same frames with gamma 1: the estimate follows
    lin = np.clip(np.rint(255.0 * (fr / 255.0) ** 2.2), 0, 255).astype(np.uint8)
    assert estimate_camera_gamma(lin, **kw) == pytest.approx(1.0, abs=0.1)
    with pytest.raises(ValueError, match="usable pixels"):
        estimate_camera_gamma(np.zeros_like(fr), **kw)
    with pytest.raises(ValueError, match="frames"):
        estimate_camera_gamma(fr[:5], **kw)


def test_extract_checks_codec_and_settings(small_phase_scan):
    gray = dataclasses.replace(small_phase_scan, patterns=parse_patterns({**PHASE, "codec": "gray-rings"}))
    fr = wp.array(read_view_frames(small_phase_scan, small_phase_scan.views[0]), device="cpu")
    with pytest.raises(ValueError, match="phase-rings"):
        extract_phase_rings(fr, gray, PhaseRingsSettings(), 1)
    with pytest.raises(ValueError, match="PhaseSettings"):
        PhaseRingsSettings(phase={"response": "rig"})


def test_dark_view_gives_no_points(small_phase_scan):
    fr = wp.array(np.zeros((len(small_phase_scan.views[0].frames), 256, 320), np.uint8), device="cpu")
    smp, stats = extract_phase_rings(fr, small_phase_scan, PhaseRingsSettings(), 1)
    assert smp.uv.shape == (0,) and stats["samples"] == 0 and stats["pixels_decoded"] == 0


def test_bench_dense_runs_both_sides(small_phase_scan):
    lines = []
    res = bench_dense(scan_dir=small_phase_scan.folder, repeats=1, devices=["cpu"], out=lines.append)
    assert any(line.startswith("total") for line in lines) and any("points/s" in line for line in lines)
    warp_pts = res["warp"][0]["points"]
    # Same stages, same rules: the same points, to a few float32 rounding cases.
    assert abs(warp_pts - res["numpy_points"]) <= 0.005 * res["numpy_points"]
    assert all(v > 0 for v in res["numpy"].values())


# The figures on the full-size default rig (Spot, gamma 2.2 and 1.0): benchmarks/acceptance.py
# (phase-rings-default-rig); the crop above keeps the same rig's pixels.


def test_a_lone_fringe_where_the_fringe_washed_out_is_dropped_as_modulation():
    """Around a pixel whose fringe passed, most lit pixels dropped for modulation (a shadow's
    edge on a defocused view): it is the camera's noise, not a fringe, and goes too (the codec's
    LONE_FRINGE_PX and LONE_FRINGE_SHARE, ``kernels.phase.drop_lone_fringes``); a pixel among
    passing neighbours, or beside dark ones only, stays."""
    import numpy as np
    import warp as wp

    from ringscan.kernels.phase import PHASE_STATUS_NAMES, PhaseMap, drop_lone_fringes
    from ringscan.pipeline.codecs.phase_rings import LONE_FRINGE_PX, LONE_FRINGE_SHARE

    ok, dark, mod = (PHASE_STATUS_NAMES.index(n) for n in ("ok", "dark", "modulation"))
    st = np.full((20, 30), ok, np.int32)
    st[:, 10:20] = mod          # a washed-out band...
    st[:10, 10:13] = dark       # ...beside a shadow
    st[5, 14] = ok              # a lone pass in it, next to the shadow
    st[15, 15] = ok             # a lone pass in its middle
    st[:, 25:] = dark
    st[5, 26] = ok              # a pass beside dark pixels only: a small lit patch, kept
    pm = PhaseMap(t=wp.zeros(st.shape, dtype=wp.float32), modulation=wp.zeros(st.shape, dtype=wp.float32),
                  status=wp.array(st, dtype=wp.int32), sector=wp.zeros(st.shape, dtype=wp.int32),
                  flags=wp.array((st == ok).astype(np.int32).ravel(), dtype=wp.int32))
    out = drop_lone_fringes(pm, size=LONE_FRINGE_PX, share=LONE_FRINGE_SHARE).status.numpy()
    gone = np.flatnonzero((st == ok) & (out != ok))
    assert {5 * 30 + 14, 15 * 30 + 15} <= set(gone.tolist()) and 5 * 30 + 26 not in set(gone.tolist())
    assert (out[st != ok] == st[st != ok]).all() and (out.ravel()[gone] == mod).all()
    assert (st == ok).sum() - (out == ok).sum() == gone.size
