"""Shared fixtures: where the real scan data lives, and how its absence is handled.

Real data sits beside the project in ``../shared/data`` (override with ``SLAM6D_DATA``). Tests
that need it skip with a reason on a developer machine without it, but fail under ``CI=true``,
where its absence means the run would silently test less than it claims.
"""

from __future__ import annotations

import os
from pathlib import Path

import pytest

PROJECT_ROOT = Path(__file__).resolve().parent.parent


def shared_data_dir() -> Path:
    return Path(os.environ.get("SLAM6D_DATA", PROJECT_ROOT.parent / "shared" / "data"))


@pytest.fixture(scope="session")
def shared_data() -> Path:
    root = shared_data_dir()
    if not root.is_dir():
        message = f"real scan data not found at {root} (set SLAM6D_DATA)"
        if os.environ.get("CI", "").lower() == "true":
            pytest.fail(message + " — required under CI=true")
        pytest.skip(message)
    return root


@pytest.fixture(scope="session")
def artifacts_dir() -> Path:
    """Where tests leave things a person may want to look at (screenshots, videos)."""
    path = PROJECT_ROOT / "test-artifacts"
    path.mkdir(exist_ok=True)
    return path
