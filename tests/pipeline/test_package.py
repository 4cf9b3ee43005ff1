"""The package layout: every re-exported name resolves, and the formats leaf stays light."""

import ast
import importlib
import pkgutil
import subprocess
import sys
from pathlib import Path

import pytest

import ringscan.hardware
import ringscan.kernels
import ringscan.pipeline
import ringscan.tools

PACKAGES = [ringscan.kernels, ringscan.pipeline, ringscan.hardware, ringscan.tools]
MODULES = sorted(m.name for pkg in PACKAGES for m in pkgutil.walk_packages(pkg.__path__, pkg.__name__ + "."))


@pytest.mark.parametrize("name", sorted(ringscan.pipeline.__all__))
def test_pipeline_root_exports_resolve(name):
    assert getattr(ringscan.pipeline, name) is not None


def test_lazy_exports_are_the_imports_the_linter_sees():
    """Every lazily re-exported name is also a TYPE_CHECKING import of the same
    module, so import-linter sees what a module taking it from here depends on."""
    tree = ast.parse(Path(ringscan.pipeline.__file__).read_text())
    block = next(n for n in tree.body if isinstance(n, ast.If) and ast.unparse(n.test) == "TYPE_CHECKING")
    seen = {alias.name: node.module for node in block.body if isinstance(node, ast.ImportFrom) for alias in node.names}
    assert seen == ringscan.pipeline._EXPORTS


def test_unknown_root_name_is_an_attribute_error():
    with pytest.raises(AttributeError, match="no attribute 'reconstruct_scna'"):
        ringscan.pipeline.reconstruct_scna  # noqa: B018


@pytest.mark.parametrize("module", MODULES)
def test_every_module_imports_and_its_all_resolves(module):
    mod = importlib.import_module(module)
    for name in getattr(mod, "__all__", []):
        assert hasattr(mod, name), f"{module}.__all__ names {name!r}, which it does not define"


def test_formats_and_the_real_drivers_load_no_warp_and_no_open3d():
    code = ("import sys, ringscan.pipeline.formats, ringscan.hardware.devices.turntable, "
            "ringscan.hardware.devices.projector, ringscan.hardware.capture;"
            "bad = [m for m in ('warp', 'open3d') if m in sys.modules]; print(bad); sys.exit(1 if bad else 0)")
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert res.returncode == 0, res.stdout + res.stderr
