"""docs/architecture.md names every module there is, and only those: the kernels table has a row per
kernels/*.py, the pipeline table a row per package (and top-level module), and each package's row names
every module and sub-package in it. A module added, split or renamed without its line in the newcomer's map
fails here."""

from __future__ import annotations

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
DOC = (ROOT / "docs" / "architecture.md").read_text(encoding="utf-8").splitlines()


def table_rows(header: str) -> dict[str, str]:
    """The rows of the table under ``header``: first cell's code name -> the whole row."""
    start = next(i for i, line in enumerate(DOC) if line.startswith(header))
    rows = {}
    for line in DOC[start + 2:]:
        if not line.startswith("|"):
            break
        rows[re.match(r"\|\s*`([^`]+)`", line).group(1)] = line
    return rows


def modules(folder: Path) -> set[str]:
    """Module stems and sub-package names (with a trailing /) directly in ``folder``."""
    mods = {p.stem for p in folder.glob("*.py") if p.stem != "__init__"}
    return mods | {p.name + "/" for p in folder.iterdir() if (p / "__init__.py").is_file()}


def test_the_kernels_table_has_a_row_per_kernels_module():
    rows = set(table_rows("| module | stage |"))
    assert rows == {m + ".py" for m in modules(ROOT / "kernels")}


def test_the_pipeline_table_names_every_package_and_each_package_every_module():
    rows = table_rows("| package / module |")
    pipeline = ROOT / "pipeline"
    assert set(rows) == {m if m.endswith("/") else m + ".py" for m in modules(pipeline)}
    for name, row in rows.items():
        if not name.endswith("/"):
            continue
        named = set(re.findall(r"`([\w/.]+)`", row))
        missing = sorted(m for m in modules(pipeline / name) if m not in named and m.rstrip("/") not in named)
        assert not missing, f"docs/architecture.md's `{name}` row does not name {missing}"


def test_every_design_section_the_code_cites_exists():
    """Comments and docstrings cite docs/design.md by section (``design.md §7``): each one a heading there."""
    design = (ROOT / "docs" / "design.md").read_text(encoding="utf-8")
    headings = set(re.findall(r"^## §(\d+) ", design, flags=re.M))
    cited = {}
    for top in ("kernels", "pipeline", "hardware", "tools", "src"):
        for path in (ROOT / top).rglob("*.py"):
            for n in re.findall(r"design\.md §(\d+)", path.read_text(encoding="utf-8")):
                cited.setdefault(n, path.relative_to(ROOT).as_posix())
    assert cited, "no citation found: the pattern no longer matches how the code cites design.md"
    assert {n: p for n, p in cited.items() if n not in headings} == {}
