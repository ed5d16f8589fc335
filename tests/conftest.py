"""Shared fixtures. Real KITTI data is read from ../shared/data and tests that need it skip cleanly."""

from __future__ import annotations

from pathlib import Path

import pytest

REPO_ROOT = Path(__file__).resolve().parents[1]
SHARED_DATA = REPO_ROOT.parent / "shared" / "data"


@pytest.fixture(scope="session")
def shared_data() -> Path:
    """``../shared/data`` (real KITTI poses and frames); skips the test when it is absent."""
    if not (SHARED_DATA / "kitti").is_dir():
        pytest.skip("../shared/data/kitti is absent (real KITTI data is not part of the repository)")
    return SHARED_DATA
