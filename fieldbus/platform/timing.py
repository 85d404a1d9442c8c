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


class LatencyHistogram:
    """Durations (ns) counted into preallocated 1 µs bins up to ``max_us``; allocation-free ``add``.

    Longer samples land in the last bin (their exact maximum is kept); the
    percentiles are read off the bins, so they are exact to 1 µs below ``max_us``.
    """

    def __init__(self, max_us: int = 20_000) -> None:
        self.counts = np.zeros(max_us + 1, dtype=np.int64)
        self._last = max_us
        self.n = 0
        self.max_ns = 0

    def add(self, duration_ns: int) -> None:
        us = duration_ns // 1000
        self.counts[us if 0 <= us < self._last else (self._last if us > 0 else 0)] += 1
        self.n += 1
        if duration_ns > self.max_ns:
            self.max_ns = duration_ns

    def percentile_us(self, q: float) -> float:
        """The ``q``-th percentile (0-100) in µs (upper edge of its bin), 0 without samples."""
        if not self.n:
            return 0.0
        rank = max(1, int(np.ceil(q / 100.0 * self.n)))
        return float(np.searchsorted(np.cumsum(self.counts), rank)) + 1.0

    def to_json(self) -> dict[str, float | int]:
        """``cycles``, ``p50``, ``p99``, ``p99.9`` (µs, 1 µs bins) and ``max`` (µs, exact)."""
        return {
            "cycles": self.n,
            "p50": self.percentile_us(50),
            "p99": self.percentile_us(99),
            "p99.9": self.percentile_us(99.9),
            "max": round(self.max_ns / 1000, 1),
        }


class CycleLatency:
    """Per cycle: wake-up latency (actual start minus deadline) and time spent in ``exchange()``, ns."""

    def __init__(self, max_us: int = 20_000) -> None:
        self.wakeup = LatencyHistogram(max_us)
        self.exchange = LatencyHistogram(max_us)

    def to_json(self) -> dict[str, dict[str, float | int]]:
        return {"wakeup": self.wakeup.to_json(), "exchange": self.exchange.to_json()}
