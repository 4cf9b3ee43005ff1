"""Every Python block of README.md and docs/*.md that a reader runs is checked here, in the
suite, without running it: it compiles, names nothing it does not define or import
(pyflakes), and every name it imports exists where it imports it from. The slow blocks run
whole in ``make docs-check`` (``benchmarks/run_doc_blocks.py``); this catches what rots
first between those runs: a function moved to another module, a renamed one, a stray name."""

from __future__ import annotations

import ast
import importlib
import io
import sys

import pytest
from pyflakes.api import check
from pyflakes.reporter import Reporter

from tests.support.benchmark_scripts import load_benchmark

PYTHON = [(b, line, text) for b, line, lang, text in load_benchmark("run_doc_blocks").classify() if lang == "python" and b.where != "no"]


def test_the_docs_have_python_blocks_to_check():
    assert len(PYTHON) >= 15 and {b.doc for b, *_ in PYTHON} >= {"README.md", "docs/api.md", "docs/fusion.md"}


@pytest.mark.parametrize("block, line, text", PYTHON, ids=[f"{b.doc}:{line}" for b, line, _ in PYTHON])
def test_python_block_names_only_what_it_defines_or_imports(block, line, text):
    out = io.StringIO()
    problems = check(text, f"{block.doc}:{line}", Reporter(out, out))
    assert problems == 0, out.getvalue()


@pytest.mark.parametrize("block, line, text", PYTHON, ids=[f"{b.doc}:{line}" for b, line, _ in PYTHON])
def test_python_block_imports_exist(block, line, text):
    for node in ast.walk(ast.parse(text)):
        if isinstance(node, ast.Import):
            for alias in node.names:
                importlib.import_module(alias.name)
        elif isinstance(node, ast.ImportFrom) and node.level == 0:
            module = importlib.import_module(node.module)
            for alias in node.names:
                if not hasattr(module, alias.name):  # a submodule not imported by its package yet
                    importlib.import_module(f"{node.module}.{alias.name}")
            assert node.module in sys.modules


def test_a_wrong_import_or_a_stray_name_fails_here():
    """The two faults docs/virtual_rig.md and docs/fusion.md once had (issue 35)."""
    with pytest.raises((ImportError, AttributeError)):
        test_python_block_imports_exist(None, 0, "from ringscan.pipeline.formats import render_frame\n")
    with pytest.raises(AssertionError, match="undefined name 'i'"):
        test_python_block_names_only_what_it_defines_or_imports(type("B", (), {"doc": "x.md"}), 1,
                                                                "for v in range(3):\n    print(i)\n")
