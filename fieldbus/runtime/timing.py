"""Cycle timing statistics with a preallocated sample buffer (no allocation per cycle)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class TimingSummary:
    """Cycle figures in µs; ``overruns`` counts cycles that missed their deadline."""

    cycles: int
    mean_us: float
    p99_us: float
    max_us: float
    overruns: int

    def to_json(self) -> dict[str, float]:
        return {"mean": round(self.mean_us, 2), "p99": round(self.p99_us, 2), "max": round(self.max_us, 2)}


class CycleTimer:
    """Collects per-cycle durations (ns) into a ring buffer of ``capacity`` samples.

    Mean and max cover every cycle; p99 covers the last ``capacity`` cycles.
    """

    def __init__(self, capacity: int = 100_000) -> None:
        self._samples = np.zeros(capacity, dtype=np.int64)
        self._n = 0
        self._sum_ns = 0
        self._max_ns = 0
        self.overruns = 0

    def add(self, duration_ns: int, *, overrun: bool = False) -> None:
        self._samples[self._n % self._samples.size] = duration_ns
        self._n += 1
        self._sum_ns += duration_ns
        if duration_ns > self._max_ns:
            self._max_ns = duration_ns
        if overrun:
            self.overruns += 1

    @property
    def cycles(self) -> int:
        return self._n

    def summary(self) -> TimingSummary:
        if not self._n:
            return TimingSummary(0, 0.0, 0.0, 0.0, 0)
        window = self._samples[: min(self._n, self._samples.size)]
        return TimingSummary(
            cycles=self._n,
            mean_us=self._sum_ns / self._n / 1000.0,
            p99_us=float(np.percentile(window, 99)) / 1000.0,
            max_us=self._max_ns / 1000.0,
            overruns=self.overruns,
        )
