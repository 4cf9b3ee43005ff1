"""../shared/data (public meshes, real captures, a real rig's numbers) for the tests that read it.

In CI (``CI`` set to true, as ``.ci/run`` runs) the folder is always there: a missing file there is a
broken path, and the test fails with one line naming it. Elsewhere (a copy of the source without
../shared) such tests skip, saying what is missing.
"""

from __future__ import annotations

import os
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]
SHARED_DATA = Path(os.environ.get("RINGSCAN_SHARED_DATA", REPO.parent / "shared" / "data"))


def in_ci() -> bool:
    return os.environ.get("CI", "").strip().lower() in ("1", "true", "yes")


def need_shared(path: Path, what: str = "") -> Path:
    """``path`` (a file or folder under ../shared/data) if it exists; else fail in CI, skip elsewhere."""
    if path.exists():
        return path
    msg = f"{what or 'shared data'} not found: {path} (../shared/data beside the repository, or RINGSCAN_SHARED_DATA)"
    if in_ci():
        pytest.fail(msg, pytrace=False)
    pytest.skip(msg)
