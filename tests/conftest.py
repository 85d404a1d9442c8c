"""Shared fixtures and paths."""

from __future__ import annotations

from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parent.parent
INTEROP = REPO / "tests" / "data" / "ethercat_driver_ros2"  # ICube ethercat_driver_ros2 files, unchanged
PDO_MAPS = REPO / "pdo_maps"


@pytest.fixture
def interop_dir() -> Path:
    if not INTEROP.is_dir():
        pytest.fail(f"interop files missing: {INTEROP}")
    return INTEROP
