"""Runtime loop: absolute deadlines, gc held, timing statistics."""

from __future__ import annotations

import gc
import time

from fieldbus.runtime.loop import gc_held, run_cycles
from fieldbus.runtime.timing import CycleTimer


def test_timer_statistics() -> None:
    t = CycleTimer(capacity=100)
    for d in range(1, 101):
        t.add(d * 1000, overrun=d > 98)
    s = t.summary()
    assert s.cycles == 100 and s.mean_us == 50.5 and s.max_us == 100.0 and s.overruns == 2
    assert 98.0 <= s.p99_us <= 100.0


def test_absolute_schedule_does_not_drift() -> None:
    stamps: list[int] = []
    t0 = time.perf_counter_ns()
    run_cycles(lambda k: stamps.append(time.perf_counter_ns()) and None, cycle_time_us=2000, cycles=100)
    elapsed_ms = (time.perf_counter_ns() - t0) / 1e6
    # 100 cycles of 2 ms: the last starts at 198 ms and the loop waits out its period.
    assert 195 <= elapsed_ms < 260, elapsed_ms
    starts = [(s - stamps[0]) / 1e6 for s in stamps]
    # absolute deadlines: cycle k starts near k * 2 ms, not k * (2 ms + jitter)
    assert abs(starts[-1] - 198.0) < 20.0, starts[-1]


def test_overrun_is_counted_and_stop_early() -> None:
    def step(k: int) -> bool:
        if k == 2:
            time.sleep(0.004)
        return k == 5

    timer = run_cycles(step, cycle_time_us=1000, cycles=100)
    assert timer.cycles == 6 and timer.overruns >= 1


def test_gc_is_disabled_inside_and_restored() -> None:
    assert gc.isenabled()
    with gc_held():
        assert not gc.isenabled()
    assert gc.isenabled()
