"""The import-linter contracts in pyproject.toml cannot be walked around.

Each case copies the package sources into a scratch folder, adds one import that
crosses a layer (or a module no layer names) and runs ``lint-imports`` on the copy:
the contract named must be broken. The unmodified copy keeps every contract.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

try:
    import tomllib
except ModuleNotFoundError:  # Python 3.10: import-linter's own TOML reader
    import tomli as tomllib

REPO = Path(__file__).resolve().parents[1]

# About 1 s per lint-imports run; the 10 runs took 10 s on a loaded 2-core machine.
pytestmark = pytest.mark.slow

# Runs lint-imports on the scratch copy only: the path entries that hold another
# ``ringscan`` (the editable install's link tree) are dropped, so the copy's
# namespace package is not merged with the real one.
_LINT = """
import os, sys
scratch = sys.argv[1]
sys.path[:] = [scratch] + [p for p in sys.path if p and not os.path.isdir(os.path.join(p, "ringscan"))]
import ringscan
where = [os.path.realpath(p) for p in ringscan.__path__]
if where != [os.path.realpath(os.path.join(scratch, "ringscan"))]:
    sys.exit(f"ringscan resolves to {where}, not the scratch copy")
from importlinter.cli import lint_imports_command
sys.argv = ["lint-imports", "--no-cache"]  # reads ./pyproject.toml (cwd: the scratch copy)
lint_imports_command()
"""


def _config() -> dict:
    with open(REPO / "pyproject.toml", "rb") as f:
        return tomllib.load(f)


def _contract_names() -> dict[str, str]:
    """Contract id -> name, from pyproject.toml."""
    return {c["id"]: c["name"] for c in _config()["tool"]["importlinter"]["contracts"]}


def _copy_sources(dst: Path) -> None:
    """The installed package's layout, from setuptools' package-dir (folder -> ringscan.*)."""
    package_dir = _config()["tool"]["setuptools"]["package-dir"]
    skip = shutil.ignore_patterns("__pycache__", "*.pyc")
    for name, folder in sorted(package_dir.items(), key=lambda kv: kv[0].count(".")):
        shutil.copytree(REPO / folder, dst.joinpath(*name.split(".")), ignore=skip, dirs_exist_ok=True)
    shutil.copy(REPO / "pyproject.toml", dst / "pyproject.toml")


def _lint(scratch: Path) -> tuple[int, dict[str, str]]:
    """lint-imports' exit code and each contract's verdict (id -> "KEPT" | "BROKEN")."""
    env = {**os.environ, "COLUMNS": "1000"}  # one contract per line
    res = subprocess.run([sys.executable, "-c", _LINT, str(scratch)], cwd=scratch, env=env,
                         capture_output=True, text=True, timeout=120)
    verdicts = {}
    lines = res.stdout.splitlines()
    for cid, name in _contract_names().items():
        for line in lines:
            if line.startswith(name + " ") and line.rsplit(" ", 1)[-1] in ("KEPT", "BROKEN"):
                verdicts[cid] = line.rsplit(" ", 1)[-1]
    assert set(verdicts) == set(_contract_names()), f"lint-imports did not report every contract:\n{res.stdout}{res.stderr}"
    return res.returncode, verdicts


@pytest.fixture(scope="module")
def pristine(tmp_path_factory) -> Path:
    scratch = tmp_path_factory.mktemp("pristine")
    _copy_sources(scratch)
    return scratch


def test_the_unmodified_copy_keeps_every_contract(pristine):
    code, verdicts = _lint(pristine)
    assert code == 0 and set(verdicts.values()) == {"KEPT"}, verdicts


def _add(path: str, text: str):
    """A change to the scratch copy: ``text`` appended to ``ringscan/<path>`` (made if new)."""
    def apply(root: Path) -> None:
        f = root / "ringscan" / path
        old = f.read_text() if f.exists() else ""
        f.write_text(old + "\n" + text + "\n")
    return apply


# (what is added, the change, the contract it must break)
CASES = [
    ("a codec imports batch through the pipeline package's re-export",
     _add("pipeline/codecs/probe.py", "from ringscan.pipeline import batch_reconstruct"), "pipeline"),
    ("a new pipeline module (in no layer) imports batch",
     _add("pipeline/export.py", "from ringscan.pipeline.batch import batch_reconstruct"), "pipeline"),
    ("a new device driver imports kernels",
     _add("hardware/devices/newcam.py", "import ringscan.kernels.raytrace"), "real-drivers"),
    ("a new device driver takes the virtual camera through the hardware package",
     _add("hardware/devices/newcam.py", "from ringscan.hardware import VirtualCamera"), "hardware"),
    ("a pipeline stage imports hardware",
     _add("pipeline/reconstruct/probe.py", "import ringscan.hardware.errors"), "top"),
    ("a kernel imports the pipeline",
     _add("kernels/launch.py", "import ringscan.pipeline.formats"), "top"),
    ("a new kernels module (in no layer)",
     _add("kernels/extra.py", "import ringscan.kernels.runtime"), "kernels"),
    ("a new hardware module (in no layer)",
     _add("hardware/extra.py", "import ringscan.hardware.errors"), "hardware"),
    ("a new top-level module (in no layer)",
     _add("extra.py", "import ringscan.tools.cli"), "top"),
    ("a pipeline stage takes the API's fuse from the package root",
     _add("pipeline/fusion/probe.py", "from ringscan import fuse"), "top"),
    ("the API imports hardware (its sibling layer)",
     _add("api.py", "import ringscan.hardware.errors"), "top"),
]


@pytest.mark.parametrize(("change", "contract"), [pytest.param(c, k, id=d) for d, c, k in CASES])
def test_an_import_across_a_layer_breaks_its_contract(pristine, tmp_path, change, contract):
    scratch = tmp_path / "copy"
    shutil.copytree(pristine, scratch)
    change(scratch)
    code, verdicts = _lint(scratch)
    assert code != 0 and verdicts[contract] == "BROKEN", verdicts
