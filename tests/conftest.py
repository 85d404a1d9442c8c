"""Shared fixtures and paths."""

from __future__ import annotations

import os
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


@pytest.hookimpl(optionalhook=True)  # pytest-xdist's hook: a plain pytest without it runs the suite too
def pytest_xdist_auto_num_workers(config: pytest.Config) -> int | None:
    """``-n auto`` (scripts/test): one worker per CPU this process may use, at most two.

    The suite is mostly single-threaded Python, so a second worker halves it on two CPUs (7 min
    instead of 14 on a quiet 2-CPU VM). Two is what the suite is kept green at beside four CPU
    burners: each more worker is more load for the tests that run real emulator processes, veth
    pairs and DDS participants on the wall clock. ``PYTEST_XDIST_AUTO_NUM_WORKERS`` still decides
    when set (None: pytest-xdist's own hook reads it).
    """
    if os.environ.get("PYTEST_XDIST_AUTO_NUM_WORKERS"):
        return None
    return max(1, min(2, len(os.sched_getaffinity(0))))
