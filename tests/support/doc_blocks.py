"""The docs' command blocks as ``benchmarks/run_doc_blocks.py`` lists and classifies them."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]


def load_run_doc_blocks():
    """``benchmarks/run_doc_blocks.py`` as a module (it is a script, not a package module)."""
    spec = importlib.util.spec_from_file_location("run_doc_blocks", ROOT / "benchmarks" / "run_doc_blocks.py")
    mod = importlib.util.module_from_spec(spec)
    sys.modules.setdefault("run_doc_blocks", mod)  # dataclasses look their module up there
    spec.loader.exec_module(mod)
    return mod
