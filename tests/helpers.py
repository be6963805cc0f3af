"""Shared test helpers (import as ``from helpers import shared_data, require_open3d``).

Real validation data live in ``../shared/data`` beside the repository (override with
``MINEGEO_SHARED_DATA``). Tests that need it call :func:`shared_data`; when the data are
missing they are skipped with a clear reason, unless ``MINEGEO_REQUIRE_SHARED_DATA=1``
(set by ``.ci/run``), in which case they fail.
"""

from __future__ import annotations

import os
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
SHARED_DATA = Path(os.environ.get("MINEGEO_SHARED_DATA", REPO.parent / "shared" / "data"))
REQUIRE_SHARED = os.environ.get("MINEGEO_REQUIRE_SHARED_DATA", "") == "1"


def shared_data(*parts: str) -> Path:
    """Path inside the shared real-data folder; skip (or fail under CI) when it is missing."""
    p = SHARED_DATA.joinpath(*parts)
    if not p.exists():
        msg = f"shared real data not found: {p} (set MINEGEO_SHARED_DATA or place ../shared/data)"
        if REQUIRE_SHARED:
            pytest.fail(msg + " and MINEGEO_REQUIRE_SHARED_DATA=1")
        pytest.skip(msg)
    return p


def require_open3d():
    """Import Open3D for oracle tests, or skip with a reason (fail if the CI requires shared data)."""
    try:
        import open3d as o3d  # noqa: F401
    except Exception as exc:  # pragma: no cover - depends on environment
        if REQUIRE_SHARED:
            pytest.fail(f"open3d is required in CI for oracle tests: {exc}")
        pytest.skip(f"open3d not available: {exc}")
    return o3d
