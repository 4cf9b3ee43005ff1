"""A scan captured through the hardware layer (emulated turntable and projector on
ptys, real drivers, virtual camera) reconstructs as well as a simulated scan of the
same scene: the two differ only in sensor noise. Small version of
benchmarks/capture_vs_simulate.py (which runs the issue's 8 views x 28 frames)."""

import pytest

from ringscan.hardware.capture.sequence import CaptureSettings, capture_scan
from ringscan.hardware.devices.grbl import GrblTurntable
from ringscan.hardware.devices.projector import SerialProjector
from ringscan.hardware.emulators.rig import EmulatedRig
from ringscan.pipeline.formats.patterns import frame_names
from tests.support.hardware_rig import small_patterns, small_rig


@pytest.mark.slow
def test_captured_scan_reconstructs_like_a_simulated_one(tmp_path):
    from ringscan.pipeline.evaluate.metrics import evaluate_recon
    from ringscan.pipeline.reconstruct.scan import reconstruct_scan
    from ringscan.pipeline.simulate.scan import simulate_scan

    rig = small_rig()
    patterns = small_patterns(bits=3, sector_bits=2)  # 12 frames; the sector code picks the root
    sim = simulate_scan(tmp_path / "sim", scene="terrain", rig=rig, patterns=patterns, views=2, device="cpu",
                        progress=False)
    with EmulatedRig(rig, patterns, "terrain", time_scale=1000.0, seed=1, device="cpu") as emu:
        tt = GrblTurntable(emu.turntable_port)
        pj = SerialProjector(emu.projector_port, expect_names=frame_names(patterns))
        cap = capture_scan(tmp_path / "cap", camera=emu.camera, projector=pj, turntable=tt, rig=rig,
                           patterns=patterns, views=2, progress=False,
                           settings=CaptureSettings(turntable_settle_s=0.0, projector_settle_s=0.0))
        tt.close()
        pj.close()
    # the captured views are where the table's steps reached: 1600 steps at 8.889 steps/deg
    assert [v.turntable_deg for v in sim.views] == [0.0, 180.0]
    assert [v.turntable_deg for v in cap.views] == [0.0, round(1600 / 8.889, 3)]

    fig = {}
    for name, scan in (("sim", sim), ("cap", cap)):
        rep = reconstruct_scan(scan, tmp_path / f"recon_{name}", device="cpu", progress=False)
        ev = evaluate_recon(tmp_path / f"recon_{name}", sim)  # both against the simulated truth
        fig[name] = dict(ev["all"], points=rep["totals"]["points"])
    s, c = fig["sim"], fig["cap"]
    assert s["points"] > 1000 and s["median_mm"] < 0.1  # the simulated scan itself is good
    assert abs(c["points"] / s["points"] - 1) < 0.03
    assert abs(c["coverage_mean"] - s["coverage_mean"]) < 0.02
    assert c["median_mm"] < 1.25 * s["median_mm"] and c["p95_mm"] < 1.25 * s["p95_mm"]
    assert c["frac_over_1mm"] <= s["frac_over_1mm"] + 0.005
