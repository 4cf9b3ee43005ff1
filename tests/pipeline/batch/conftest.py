"""Tiny simulated scans for the batch tests (320x256 camera, one view each)."""

import pytest

from ringscan.pipeline.formats.patterns import parse_patterns
from ringscan.pipeline.simulate.scan import simulate_scan
from tests.pipeline.reconstruct.test_reconstruct import PROJ, small_rig

SPEC = {"codec": "gray-rings", **PROJ, "rho0": 8.0, "pitch": 16.0, "bits": 5, "sector_bits": 4}


@pytest.fixture(scope="package")
def scan_root(tmp_path_factory):
    """Two scans: ``a_sphere`` and ``b/cube``."""
    root = tmp_path_factory.mktemp("batch") / "scans"
    spec = parse_patterns(SPEC)
    for name, scene in (("a_sphere", "sphere"), ("b/cube", "cube")):
        simulate_scan(root / name, scene=scene, rig=small_rig(), patterns=spec, progress=False)
    return root


@pytest.fixture(scope="package")
def three_scans(tmp_path_factory, scan_root):
    """Three scans, one of two views (``c_turn``)."""
    import shutil

    root = tmp_path_factory.mktemp("batch3") / "scans"
    shutil.copytree(scan_root, root)
    simulate_scan(root / "c_turn", scene="sphere", rig=small_rig(), patterns=parse_patterns(SPEC),
                  turntable_deg=(0.0, 120.0), progress=False)
    return root
