"""Adding a codec = one PatternLayout (data level) + one Codec module + one registry
entry (docs/architecture.md). This test adds a small real codec, an intensity-ratio
ramp (white, black, and a frame whose light rises linearly with rho), registers it,
and runs it end to end: simulate a scan, reconstruct it, compare with the truth."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np
import pytest
import warp as wp

from ringscan.kernels.samples import Samples
from ringscan.pipeline.codecs import registry
from ringscan.pipeline.codecs.base import Codec, StageSettings
from ringscan.pipeline.codecs.drawing import polar, to_u8
from ringscan.pipeline.evaluate.metrics import evaluate_recon
from ringscan.pipeline.formats import patterns
from ringscan.pipeline.formats.patterns import Parameter, PatternLayout, PatternSpec, parse_patterns
from ringscan.pipeline.formats.rig import default_rig
from ringscan.pipeline.formats.scan import Scan
from ringscan.pipeline.reconstruct.scan import reconstruct_scan
from ringscan.pipeline.simulate.scan import simulate_scan


class RampLayout(PatternLayout):
    name = "ramp"
    dense = True
    parameters = (Parameter("bits", int, None, 1, 16, doc="the ramp spans 2**bits bands of pitch px"),)

    def frame_names(self, spec: PatternSpec) -> list[str]:
        return ["white", "black", "ramp"]


@dataclass(frozen=True)
class RampSettings:
    min_contrast: float = 12.0
    """Least white - black (8-bit levels)."""


class RampCodec(Codec[RampSettings]):
    layout = RampLayout()
    settings_type = RampSettings

    def render_frame(self, spec: PatternSpec, name: str) -> np.ndarray:
        if name != "ramp":
            return np.full((spec.height, spec.width), 255 if name == "white" else 0, np.uint8)
        rho, _ = polar(spec)
        return to_u8(spec, (rho - spec.rho0) / (spec.rho_max - spec.rho0))

    def settings_from(self, stages: StageSettings) -> RampSettings:
        return RampSettings(min_contrast=stages.decode.min_contrast)

    def extract(self, frames: wp.array, scan: Scan, settings: RampSettings, *, threads: int) -> tuple[Samples, dict]:
        spec, f = scan.patterns, frames.numpy().astype(np.float64)
        white, black, ramp = (f / 255.0) ** scan.rig.camera.gamma          # irradiance
        t = (np.clip((ramp - black) / np.maximum(white - black, 1e-9), 0, 1)) ** (1.0 / scan.rig.light.gamma)
        ok = (f[0] - f[1] >= settings.min_contrast) & (t > 0.02) & (t < 0.98)
        pix = np.flatnonzero(ok.ravel()).astype(np.int32)
        w = f.shape[2]

        def warp_array(a, dtype):
            return wp.array(a, dtype=dtype, device=frames.device)

        samples = Samples(uv=warp_array(np.stack([pix % w, pix // w], 1).astype(np.float32), wp.vec2),
                          rho=warp_array((spec.rho0 + t.ravel()[pix] * (spec.rho_max - spec.rho0)).astype(np.float32),
                                         wp.float32),
                          ring=None, sector=warp_array(np.full(pix.size, -1, np.int32), wp.int32),
                          confidence=warp_array(np.ones(pix.size, np.float32), wp.float32),
                          pixel=warp_array(pix, wp.int32))
        return samples, {"pixels_decoded": int(pix.size), "samples": int(pix.size), "times_s": {"decode": 0.0}}


@pytest.fixture
def ramp_registered(monkeypatch):
    codec = RampCodec()
    monkeypatch.setitem(patterns.PATTERN_LAYOUTS, codec.name, codec.layout)
    monkeypatch.setitem(registry.REGISTRY, codec.name, codec)
    return codec


def test_a_registered_codec_runs_end_to_end(ramp_registered, tmp_path):
    rig = default_rig(gamma=2.2)
    K = rig.camera.K.copy()
    K[0, 2] -= (rig.camera.width - 320) / 2
    K[1, 2] -= (rig.camera.height - 256) / 2
    rig = dataclasses.replace(rig, camera=dataclasses.replace(rig.camera, width=320, height=256, K=K))
    spec = parse_patterns({"codec": "ramp", "width": 1024, "height": 768, "center": [511.5, 383.5], "rho0": 8.0,
                           "pitch": 8.0, "bits": 5})
    assert spec.to_dict()["bits"] == 5 and spec.rho_max == 8.0 + 32 * 8.0
    # what the rest of the pipeline asks of a codec, the codec says from its own files
    assert ramp_registered.calibrates_light and not ramp_registered.has_angle_code
    assert not ramp_registered.full_coordinate(spec)
    scan = simulate_scan(tmp_path / "scan", scene="sphere", rig=rig, patterns=spec, progress=False)
    assert [n for n in scan.views[0].frames] == ["white", "black", "ramp"]
    rep = reconstruct_scan(scan, tmp_path / "rec", progress=False)
    view = rep["views"][0]
    ev = evaluate_recon(tmp_path / "rec", scan)["views"]["view_000"]
    assert view["points"] > 10_000
    # an 8-bit intensity ratio is coarse (measured 1.1 mm); without the camera's
    # gamma undone the same scan gives 3.7 mm
    assert ev["median_mm"] < 2.0
