"""Allocation accounting for the hot path (tracemalloc based).

``net_blocks(step, cycles)`` runs ``step`` ``warmup`` times, then measures how
many memory blocks stay allocated after a further ``cycles`` calls. One-off
caches filled on first use are excluded by the warm-up window, so a cycle that
allocates nothing gives 0 (a leak of one block per cycle gives ``cycles``).
"""

from __future__ import annotations

import gc
import tracemalloc
from collections.abc import Callable

_IGNORE = (tracemalloc.Filter(False, tracemalloc.__file__), tracemalloc.Filter(False, "<unknown>"))


def _blocks() -> int:
    snap = tracemalloc.take_snapshot().filter_traces(_IGNORE)
    return sum(stat.count for stat in snap.statistics("filename"))


def net_blocks(step: Callable[[], object], cycles: int = 10_000, warmup: int = 1_000) -> int:
    """Net blocks still allocated after ``cycles`` calls of ``step`` (after a warm-up)."""
    was_tracing = tracemalloc.is_tracing()
    if not was_tracing:
        tracemalloc.start()
    try:
        for _ in range(warmup):
            step()
        gc.collect()
        before = _blocks()
        for _ in range(warmup):  # second warm-up: anything the first snapshot itself cached
            step()
        gc.collect()
        before = _blocks()
        for _ in range(cycles):
            step()
        gc.collect()
        return _blocks() - before
    finally:
        if not was_tracing:
            tracemalloc.stop()
