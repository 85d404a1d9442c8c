"""Shared helpers for the benchmarks: interleaved timing on a noisy machine.

Contenders are timed in batches of cycles; every round runs one batch of each
contender in a shuffled order, so slow phases of the machine hit all of them.
Report medians over rounds, and ratios taken *within* a round (paired), not
the best run of each contender on its own.
"""

from __future__ import annotations

import os
import platform
import random
import statistics
import sys
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np

Step = Callable[[], object]


class RoundProgress:
    """``round 3/10 (30%) ... s left`` on stderr while a benchmark runs; nothing when stderr is no terminal."""

    def __init__(self, total: int) -> None:
        self.total = total
        self.done = 0
        self.t0 = time.perf_counter_ns()
        self.stream = sys.stderr if sys.stderr.isatty() else None

    def step(self) -> None:
        from fieldbus.platform.loop import progress

        self.done += 1
        if self.stream is not None:
            line = progress(self.done, self.total, time.perf_counter_ns() - self.t0, "round")
            self.stream.write(f"\r{line}   " + ("\n" if self.done >= self.total else ""))
            self.stream.flush()


def cycles_per_batch(step: Step, target_s: float, max_cycles: int = 1_000_000) -> int:
    """How many calls of ``step`` take about ``target_s`` (measured, at least 1)."""
    n = 1
    while True:
        t0 = time.perf_counter()
        for _ in range(n):
            step()
        dt = time.perf_counter() - t0
        if dt >= target_s / 4 or n >= max_cycles:
            return max(1, min(max_cycles, round(n * target_s / max(dt, 1e-9))))
        n *= 4


def time_batch(step: Step, cycles: int) -> float:
    """Seconds per call of ``step``, over one batch of ``cycles`` calls."""
    t0 = time.perf_counter_ns()
    for _ in range(cycles):
        step()
    return (time.perf_counter_ns() - t0) / 1e9 / cycles


@dataclass
class Samples:
    """Per-round seconds-per-cycle of each contender (same round index = same round)."""

    per_round: dict[str, list[float]] = field(default_factory=dict)

    def median_us(self, name: str) -> float:
        return statistics.median(self.per_round[name]) * 1e6

    def quartiles_us(self, name: str) -> tuple[float, float]:
        q = np.percentile(self.per_round[name], [25, 75]) * 1e6
        return float(q[0]), float(q[1])

    def ratio(self, name: str, base: str) -> float:
        """Median over rounds of name/base within the same round."""
        return statistics.median(
            a / b for a, b in zip(self.per_round[name], self.per_round[base], strict=True)
        )

    def ratio_quartiles(self, name: str, base: str) -> tuple[float, float]:
        r = [a / b for a, b in zip(self.per_round[name], self.per_round[base], strict=True)]
        q = np.percentile(r, [25, 75])
        return float(q[0]), float(q[1])


def interleaved(
    groups: Mapping[str, Mapping[str, Step]],
    rounds: int,
    batch_s: float,
    seed: int = 0,
) -> dict[str, Samples]:
    """Time every contender of every group, ``rounds`` times, interleaved.

    ``groups`` maps a group (for example "12 axes") to its contenders. Each
    round visits the groups in order and the contenders of a group in a fresh
    random order, one batch of about ``batch_s`` seconds each.
    """
    rng = random.Random(seed)
    batches = {g: {c: cycles_per_batch(s, batch_s) for c, s in cs.items()} for g, cs in groups.items()}
    out = {g: Samples({c: [] for c in cs}) for g, cs in groups.items()}
    shown = RoundProgress(rounds)
    for _ in range(rounds):
        for g, cs in groups.items():
            order = list(cs)
            rng.shuffle(order)
            for c in order:
                out[g].per_round[c].append(time_batch(cs[c], batches[g][c]))
        shown.step()
    return out


def machine_note() -> str:
    """One line about the host: CPU count, Python, numpy, platform."""
    return (
        f"{os.cpu_count()} CPUs, {platform.machine()}, Python {platform.python_version()}, "
        f"numpy {np.__version__}, {platform.system()} {platform.release()}"
    )


def table(header: Sequence[str], rows: Sequence[Sequence[str]]) -> str:
    """A GitHub-markdown table (also readable on a terminal)."""
    widths = [max(len(str(r[i])) for r in [header, *rows]) for i in range(len(header))]

    def line(cells: Sequence[str]) -> str:
        return "| " + " | ".join(str(c).ljust(w) for c, w in zip(cells, widths, strict=True)) + " |"

    sep = "|" + "|".join("-" * (w + 2) for w in widths) + "|"
    return "\n".join([line(header), sep, *(line(r) for r in rows)])
