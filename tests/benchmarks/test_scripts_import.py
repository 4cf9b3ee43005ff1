"""Every benchmark script's ``ringscan`` imports name something ringscan has: a script is not run by the
suite (most take minutes), so a name moved or renamed in the package would otherwise break it unseen
(``kernel_stages.py`` and ``kernel_replay.py`` once imported ``retain_freed_memory`` from the module it
had left)."""

import ast
import importlib
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
SCRIPTS = sorted((ROOT / "benchmarks").glob("*.py"))


def ringscan_imports(tree: ast.AST) -> list[tuple[str, str | None, int]]:
    """(module, name or None for ``import module``, line) of every ``ringscan`` import in ``tree``, at any
    depth (scripts import some names inside functions), in line order."""
    out = []
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom) and node.level == 0 and (node.module or "").split(".")[0] == "ringscan":
            out += [(node.module, a.name, node.lineno) for a in node.names]
        elif isinstance(node, ast.Import):
            out += [(a.name, None, node.lineno) for a in node.names if a.name.split(".")[0] == "ringscan"]
    return sorted(out, key=lambda t: t[2])


def missing_imports(path: Path) -> list[str]:
    """``file:line: module.name`` for each ringscan import of ``path`` that does not resolve."""
    bad = []
    for module, name, line in ringscan_imports(ast.parse(path.read_text(), filename=str(path))):
        try:
            mod = importlib.import_module(module)
        except ImportError:
            bad.append(f"{path.name}:{line}: {module}")
            continue
        if name is not None and name != "*" and not hasattr(mod, name):
            try:  # a submodule imported by name (``from ringscan.kernels import runtime``)
                importlib.import_module(f"{module}.{name}")
            except ImportError:
                bad.append(f"{path.name}:{line}: {module}.{name}")
    return bad


def test_the_check_finds_a_name_the_package_does_not_have(tmp_path):
    script = tmp_path / "stale.py"
    script.write_text("def main():\n    from ringscan.kernels.runtime import retain_freed_memory\n"
                      "from ringscan.kernels import process\nimport ringscan.no_such_module\n")
    assert missing_imports(script) == ["stale.py:2: ringscan.kernels.runtime.retain_freed_memory",
                                       "stale.py:4: ringscan.no_such_module"]


@pytest.mark.parametrize("script", SCRIPTS, ids=[p.name for p in SCRIPTS])
def test_every_ringscan_name_a_benchmark_imports_exists(script):
    assert missing_imports(script) == []
