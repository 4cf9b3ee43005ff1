"""benchmarks/layout_report.py: a long or wide function counts as explained by a docstring line ``Size:``."""

import textwrap
from pathlib import Path

from tests.support.benchmark_scripts import load_benchmark

ROOT = Path(__file__).resolve().parents[2]


def _layout_report():
    return load_benchmark("layout_report")


def test_size_line_explains_a_long_or_wide_function(tmp_path):
    report = _layout_report()
    body = "\n".join(f"    x{i} = {i}" for i in range(report.LONG_FUNCTION + 1))
    wide = ", ".join(f"p{i}" for i in range(report.MANY_PARAMETERS + 1))
    source = textwrap.dedent('''\
        def long_explained():
            """Does a lot.

            Size: one loop whose parts share every local.
            """
        {body}


        def long_unexplained():
            """Does a lot, says not why (the word Size: mid-line does not count)."""
        {body}


        def wide_explained({wide}):
            """Size: one argument per array."""


        def wide_unexplained(self, {wide}):
            pass


        def small(a, b):
            pass
        ''').format(body=body, wide=wide)
    (tmp_path / "mod.py").write_text(source, encoding="utf-8")
    long_fns, wide_fns = report.oversized([tmp_path / "mod.py"], root=tmp_path)
    assert sorted((where.split()[1], ok) for _, where, ok in long_fns) == [
        ("long_explained", True), ("long_unexplained", False)]
    assert sorted((where.split()[1], ok) for _, where, ok in wide_fns) == [
        ("wide_explained", True), ("wide_unexplained", False)]
    assert all(where.startswith("mod.py:") for _, where, _ in long_fns + wide_fns)
