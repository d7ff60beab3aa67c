"""Shared fixtures for the scan I/O tests: the real LiDAR files in ../shared/fixtures/real."""
from __future__ import annotations

from pathlib import Path

import pytest

REAL = Path(__file__).resolve().parents[3] / "shared/fixtures/real"


@pytest.fixture(scope="session")
def real_dir() -> Path:
    """The real-files folder, or a skip saying where it was expected."""
    if not REAL.is_dir():
        pytest.skip(f"real LiDAR fixtures not found at {REAL} (expected ../shared/fixtures/real from the repo root)")
    return REAL
