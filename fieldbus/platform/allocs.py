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


def _snapshot() -> tracemalloc.Snapshot:
    return tracemalloc.take_snapshot().filter_traces(_IGNORE)


def _blocks(snap: tracemalloc.Snapshot) -> int:
    return sum(stat.count for stat in snap.statistics("filename"))


def net_blocks(
    step: Callable[[], object], cycles: int = 10_000, warmup: int = 1_000, *, sites: list[str] | None = None
) -> int:
    """Net blocks still allocated after ``cycles`` calls of ``step`` (after a warm-up).

    ``sites``: a list to fill with the lines that hold more blocks than before
    (``file:line +n``, largest first), to say where a count came from.
    """
    was_tracing = tracemalloc.is_tracing()
    if not was_tracing:
        tracemalloc.start()
    try:
        for _ in range(warmup):
            step()
        gc.collect()
        _snapshot()
        for _ in range(warmup):  # second warm-up: anything the first snapshot itself cached
            step()
        gc.collect()
        before = _snapshot()
        for _ in range(cycles):
            step()
        gc.collect()
        after = _snapshot()
        if sites is not None:
            sites.extend(
                f"{d.traceback[0].filename}:{d.traceback[0].lineno} +{d.count_diff}"
                for d in after.compare_to(before, "lineno")
                if d.count_diff > 0
            )
        return _blocks(after) - _blocks(before)
    finally:
        if not was_tracing:
            tracemalloc.stop()
