"""Shared fixtures. Module-specific fixtures live in their own test modules."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

# ../shared/data beside the project (override with SPLIDAR_SHARED_DATA)
_DEFAULT_SHARED = Path(__file__).resolve().parents[2] / "shared" / "data"


def shared_data_dir() -> Path | None:
    p = Path(os.environ.get("SPLIDAR_SHARED_DATA", _DEFAULT_SHARED))
    return p if p.is_dir() else None


@pytest.fixture(scope="session")
def shared_data() -> Path:
    """Folder of the public real data sets; skips the test when it is absent."""
    p = shared_data_dir()
    if p is None:
        pytest.skip("../shared/data is absent (real data sets are not part of a fresh clone)")
    return p
