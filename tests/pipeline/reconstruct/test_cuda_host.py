"""A view's host code works with Warp arrays as CUDA's behave, on the CPU backend.

A CPU Warp array is NumPy memory: ``np.asarray`` views it, ``.numpy()`` is a view
(writes to it reach the Warp array), and ``wp.launch`` takes NumPy arrays in its
place. A CUDA array does none of that: ``np.asarray`` raises, ``.numpy()`` is a
copy, and a NumPy array given to a CUDA launch is an error. Host code that leans on
the CPU's ways works in every test here and breaks on a user's first GPU run. These
tests give the CPU arrays CUDA's host behaviour and reconstruct a view of every
codec (and a two-camera view): the same points, byte for byte, and no forbidden use.
"""

from __future__ import annotations

import dataclasses
import os
import sys

import numpy as np
import pytest
import warp as wp

from ringscan.kernels import init_warp
from ringscan.pipeline.formats.patterns import parse_patterns
from ringscan.pipeline.formats.rig import default_rig
from ringscan.pipeline.reconstruct.view import reconstruct_view
from ringscan.pipeline.simulate.scan import simulate_scan
from tests.support.tiny_scan import TINY_PATTERNS, tiny_rig
from tests.support.two_camera_scan import simulate_decoded_two_camera_scan

init_warp()
WARP_DIR = os.path.dirname(wp.__file__)
CLOUD_FIELDS = ("points", "ring", "rho", "confidence", "uv", "sigma", "residual")


@pytest.fixture
def cuda_host_arrays(monkeypatch):
    """Warp arrays behave on the host as CUDA arrays do (Warp's own code keeps its
    access); returns the list of forbidden uses seen (each also raises where it happens)."""
    seen: list[str] = []

    def caller_is_warp(depth: int) -> bool:
        return sys._getframe(depth).f_code.co_filename.startswith(WARP_DIR)

    interface = wp.array.__array_interface__

    def array_interface(self):
        if not caller_is_warp(2):
            seen.append("np.asarray of a Warp array")
            raise AttributeError("__array_interface__: not for a CUDA array")
        return interface.fget(self)

    def array_protocol(self):
        if caller_is_warp(2):
            raise AttributeError("__array__")  # as on the CPU: Warp's own conversions use the interface
        seen.append("np.asarray of a Warp array")

        def reject(dtype=None, copy=None):
            raise TypeError("a CUDA array has no implicit NumPy conversion: call .numpy()")

        return reject

    to_numpy = wp.array.numpy

    def numpy_copy(self, **kw):
        return np.array(to_numpy(self, **kw), copy=True)  # a device-to-host copy, never a view

    launch = wp.launch

    def launch_without_numpy(kernel, dim=None, inputs=(), outputs=(), *args, **kw):
        if any(isinstance(a, np.ndarray) for a in [*(inputs or ()), *(outputs or ())]):
            seen.append(f"a NumPy array given to wp.launch({kernel.key})")
            raise RuntimeError("a CUDA launch takes Warp arrays, not NumPy arrays")
        return launch(kernel, dim, inputs, outputs, *args, **kw)

    monkeypatch.setattr(wp.array, "__array_interface__", property(array_interface))
    monkeypatch.setattr(wp.array, "__array__", property(array_protocol))
    monkeypatch.setattr(wp.array, "numpy", numpy_copy)
    monkeypatch.setattr(wp, "launch", launch_without_numpy)
    return seen


def test_the_fixture_forbids_what_cuda_forbids(cuda_host_arrays):
    a = wp.zeros(3, dtype=wp.float32, device="cpu")
    with pytest.raises(TypeError, match="implicit NumPy conversion"):
        np.asarray(a)
    b = a.numpy()
    b[0] = 5.0
    assert a.numpy()[0] == 0.0  # a copy: the Warp array is unchanged

    @wp.kernel
    def _fill(out: wp.array(dtype=wp.float32)):
        out[wp.tid()] = 1.0

    with pytest.raises(RuntimeError, match="Warp arrays, not NumPy"):
        wp.launch(_fill, dim=3, inputs=[], outputs=[np.zeros(3, np.float32)], device="cpu")
    assert set(cuda_host_arrays) == {"np.asarray of a Warp array", "a NumPy array given to wp.launch(" + _fill.key + ")"}


def _small_rings_scan(folder):
    """The single-shot codec on the default rig with a 320x256 camera (the tiny rig shows its rings too small)."""
    rig = default_rig()
    K = np.array([[650.0, 0, 159.5], [0, 650.0, 127.5], [0, 0, 1]])
    rig = dataclasses.replace(rig, camera=dataclasses.replace(rig.camera, width=320, height=256, K=K))
    spec = parse_patterns({"codec": "rings", "width": 1024, "height": 768, "center": [511.5, 383.5], "rho0": 40.0,
                           "pitch": 40.0, "count": 9, "line_width": 8.0})
    return simulate_scan(folder, scene="sphere", rig=rig, patterns=spec, progress=False)


@pytest.fixture(scope="module")
def scans(tmp_path_factory):
    def tiny(name, **extra):
        patterns = parse_patterns({**TINY_PATTERNS, **extra})
        return simulate_scan(tmp_path_factory.mktemp(name) / "scan", scene="sphere", size_mm=40.0, rig=tiny_rig(),
                             patterns=patterns, progress=False)

    phase = {"codec": "phase-rings", "pitch": 12.0, "steps": 4}
    return {
        "gray-rings + angle": tiny("angle", angle_steps=4),
        "phase-rings": tiny("phase", **phase),
        "rings": _small_rings_scan(tmp_path_factory.mktemp("rings") / "scan"),
        "decoded, two cameras": simulate_decoded_two_camera_scan(tmp_path_factory.mktemp("two") / "scan"),
    }


@pytest.mark.parametrize("name", ["gray-rings + angle", "phase-rings", "rings", "decoded, two cameras"])
def test_a_view_with_cuda_host_arrays_gives_the_same_points(scans, name, request):
    scan = scans[name]
    plain = reconstruct_view(scan, scan.views[0], device="cpu")
    seen = request.getfixturevalue("cuda_host_arrays")
    cuda_like = reconstruct_view(scan, scan.views[0], device="cpu")
    assert seen == []
    assert plain.points.shape[0] > 200, plain.stats
    for k in CLOUD_FIELDS:
        a, b = getattr(plain, k), getattr(cuda_like, k)
        if a is None:
            assert b is None, k
            continue
        assert a.dtype == b.dtype and a.shape == b.shape and a.tobytes() == b.tobytes(), k
