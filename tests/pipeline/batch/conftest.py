"""Fixtures of the batch tests: folders of the small simulated scans of tests/support/batch_scans.py."""

import pytest

from tests.support.batch_scans import simulate_batch_scan


@pytest.fixture(scope="package")
def scan_root(tmp_path_factory):
    """Two scans: ``a_sphere`` and ``b/cube``."""
    root = tmp_path_factory.mktemp("batch") / "scans"
    for name, scene in (("a_sphere", "sphere"), ("b/cube", "cube")):
        simulate_batch_scan(root / name, scene)
    return root


@pytest.fixture(scope="package")
def three_scans(tmp_path_factory, scan_root):
    """Three scans, one of two views (``c_turn``)."""
    import shutil

    root = tmp_path_factory.mktemp("batch3") / "scans"
    shutil.copytree(scan_root, root)
    simulate_batch_scan(root / "c_turn", "sphere", turntable_deg=(0.0, 120.0))
    return root
