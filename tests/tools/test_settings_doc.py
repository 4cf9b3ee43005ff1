"""docs/settings.md is what ``benchmarks/settings_doc.py`` writes from ``ringscan schema``: every settings field,
with its default and docstring, as the code has them now."""

from __future__ import annotations

import json
from pathlib import Path

from tests.support.benchmark_scripts import load_benchmark

ROOT = Path(__file__).resolve().parents[2]


def _script():
    return load_benchmark("settings_doc")


def test_settings_md_is_up_to_date():
    assert (ROOT / "docs" / "settings.md").read_text() == _script().render(), (
        "docs/settings.md is out of date: run `python benchmarks/settings_doc.py` and commit it")


def test_settings_md_lists_every_field_of_the_schemas(capsys):
    """Each field `ringscan schema settings|capture-settings` prints is a row, by the path --set names."""
    from ringscan.tools.cli import main

    text = (ROOT / "docs" / "settings.md").read_text()
    for what in ("settings", "capture-settings"):
        assert main(["schema", what]) == 0
        schema = json.loads(capsys.readouterr().out)
        for name, prop in schema["properties"].items():
            assert f"| `{name}` |" in text, (what, name)
            ref = prop.get("$ref", "").rsplit("/", 1)[-1]
            for field in schema.get("$defs", {}).get(ref, {}).get("properties", {}):
                assert f"| `{name}.{field}` |" in text, (what, name, field)
    assert "| `triangulate.constraint` | string | `\"auto\"` | Which projector coordinates" in text
