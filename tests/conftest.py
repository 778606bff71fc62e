"""Fixtures shared by every tier of the suite."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

REPO_ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="session")
def shared_data() -> Path:
    """The third-party data folder (``../shared/data`` beside the repository).

    Override with ``TWINDELTA_SHARED_DATA``. Fails, never skips, when it is missing: the
    real-data tests are part of the suite.
    """
    path = Path(os.environ.get("TWINDELTA_SHARED_DATA", REPO_ROOT.parent / "shared" / "data"))
    if not (path / "ycb").is_dir():
        pytest.fail(f"shared data not found at {path}; set TWINDELTA_SHARED_DATA")
    return path
