"""Gaps in the served cycle: a cycle thread the machine did not run, and the safe stop that follows.

A drive's SyncManager watchdog (100 ms by default) ends its OP when no
process data comes for that long; the bus then reads short working counters
and latches its safe stop after ``safe_stop_after`` of them. On a loaded
machine a cycle thread at normal priority can go unscheduled for that long.
:class:`StallWatch` notes every gap between two cycles' starts of at least
``STALL_PERIODS`` cycle periods and, when the bus's safe stop latches soon
after one, says so (``note``), so that the cause is in the diagnostics and the
report rather than only "working counter short".
"""

from __future__ import annotations

STALL_PERIODS = 20  # a gap of this many cycle periods between two cycles' starts is a stall
OVER_NS = 5_000_000  # gaps longer than this are counted too (``over_5ms``): the served cycle's goal, 5 ms
NOTE_WITHIN_CYCLES = 200  # a safe stop latched this many cycles after a stall is put down to it
KEEP_OVER = 64  # the newest gaps over OVER_NS kept with their times (``over_5ms_at``)


class StallWatch:
    """Call :meth:`tick` at the start of every cycle and :meth:`result` after its exchange."""

    def __init__(self, period_ns: int) -> None:
        self.period_ns = period_ns
        self.count = 0  # stalls seen
        self.longest_ns = 0
        self.longest_gap_ns = 0  # the longest gap between two cycles' starts, stall or not
        self.over_5ms = 0  # gaps longer than OVER_NS, stall or not
        # the newest KEEP_OVER of them: (the cycle that started late, the gap [ns], when it started [ns,
        # the tick's clock]), to line them up with another clock's record of the machine (a wake-up witness)
        self.over_5ms_at: list[tuple[int, int, int]] = []
        self.last_cycle = -1  # the cycle that started after the newest stall (-1: none yet)
        self.last_ns = 0  # that stall's gap
        self.note = ""  # why the newest latched safe stop came, when a stall explains it
        self._prev_ns: int | None = None
        self._stopped = False

    def tick(self, now_ns: int, cycle: int) -> None:
        """Cycle ``cycle`` starts at ``now_ns`` (any monotonic clock, ns)."""
        if self._prev_ns is not None:
            gap = now_ns - self._prev_ns
            if gap > self.longest_gap_ns:
                self.longest_gap_ns = gap
            if gap > OVER_NS:
                self.over_5ms += 1
                if len(self.over_5ms_at) == KEEP_OVER:
                    del self.over_5ms_at[0]
                self.over_5ms_at.append((cycle, gap, now_ns))
            if gap >= STALL_PERIODS * self.period_ns:
                self.count += 1
                self.longest_ns = max(self.longest_ns, gap)
                self.last_cycle, self.last_ns = cycle, gap
        self._prev_ns = now_ns

    def result(self, cycle: int, safe_stop: bool) -> None:
        """After cycle ``cycle``'s exchange: on the edge of a latched safe stop, note a recent stall."""
        if safe_stop and not self._stopped and self.last_cycle >= 0:
            after = cycle - self.last_cycle
            if after <= NOTE_WITHIN_CYCLES:
                self.note = (
                    f"safe stop latched at cycle {cycle}, {after} cycles after the cycle thread stalled "
                    f"{self.last_ns / 1e6:.0f} ms before cycle {self.last_cycle} (a drive's SyncManager "
                    "watchdog ends its OP after 100 ms by default): run the cycle at --rt-priority"
                )
        self._stopped = safe_stop
