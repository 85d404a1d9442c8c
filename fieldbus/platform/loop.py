"""The cyclic loop: absolute deadlines, gc held off, timing statistics, a status line.

``run_cycles(step, cycle_time_us, cycles)`` calls ``step(k)`` once per cycle
on an absolute schedule (deadline k * cycle time from the start, so delays do
not accumulate). The garbage collector is frozen and disabled inside the loop
and restored afterwards. A cycle that ends after its deadline counts as an
overrun; the next one starts at once and the schedule is kept (no catch-up
burst beyond one cycle: deadlines missed by more than a cycle are skipped).
"""

from __future__ import annotations

import gc
import sys
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import TextIO

from fieldbus.platform.clock import Clock, is_virtual, sleep_until
from fieldbus.platform.timing import CycleLatency, CycleTimer

# Sleep until this close to the deadline, then spin: OS sleeps overshoot by ~50-100 µs.
SPIN_NS = 150_000


@contextmanager
def gc_held() -> Iterator[None]:
    """Freeze existing objects and disable the collector; restore both on exit.

    No collection on entry: the loop starts right after bring-up, and a full
    collection of a large heap (a test run, a robot application) can take
    longer than the slaves' SyncManager watchdog (100 ms by default), during
    which no frame goes out - the drives would drop to SAFE-OP before the
    first cycle. Garbage frozen here is collected after the loop.
    """
    was_enabled = gc.isenabled()
    gc.freeze()
    gc.disable()
    try:
        yield
    finally:
        gc.unfreeze()
        if was_enabled:
            gc.enable()


def wait_until(
    deadline_ns: int,
    clock: Callable[[], int] = time.perf_counter_ns,
    sleep: Callable[[float], None] = time.sleep,
) -> None:
    """Sleep, then spin, until ``clock() >= deadline_ns`` (ns)."""
    remaining = deadline_ns - clock()
    if remaining > SPIN_NS:
        sleep((remaining - SPIN_NS) / 1e9)
    while clock() < deadline_ns:
        pass


def run_cycles(
    step: Callable[[int], bool | None],
    cycle_time_us: float,
    cycles: int,
    *,
    timer: CycleTimer | None = None,
    status: TextIO | None = None,
    status_every_s: float = 1.0,
    describe: Callable[[], str] | None = None,
    adjust: Callable[[], int] | None = None,
    latency: CycleLatency | None = None,
    clock: Clock | Callable[[], int] = time.perf_counter_ns,
    sleep: Callable[[float], None] = time.sleep,
) -> CycleTimer:
    """Run ``step(k)`` for k = 0..cycles-1 at ``cycle_time_us``; ``step`` returning True stops early.

    ``timer`` receives the duration of each ``step`` (ns). With ``status`` (e.g.
    ``sys.stderr``) a one-line status is rewritten about once per
    ``status_every_s`` using ``describe()``. ``adjust()`` (ns) is added to each
    next deadline: the DC host sync (``Operational.dc_correction_ns``). ``clock``
    is a :class:`~fieldbus.platform.clock.Clock` (its ``now_ns`` and ``sleep``; a
    :class:`~fieldbus.platform.clock.VirtualClock` jumps to each deadline, so the
    loop runs as fast as the CPU allows with the same cycles), or a ``() -> ns``
    function used with ``sleep`` (s). With ``latency`` each cycle's
    wake-up latency (start minus its deadline, ns) goes into ``latency.wakeup``;
    the caller's step adds its exchange time to ``latency.exchange``.
    """
    timer = timer or CycleTimer(capacity=max(1, min(cycles, 1_000_000)))
    source: Clock | None = clock if isinstance(clock, Clock) else None
    if source is not None:
        clock = source.now_ns
    now: Callable[[], int] = clock  # type: ignore[assignment]
    period = int(cycle_time_us * 1000)
    next_status = 0
    with gc_held():
        start = now()
        deadline = start
        for k in range(cycles):
            t0 = now()
            if latency is not None:
                latency.wakeup.add(t0 - deadline)
            stop = step(k)
            t1 = now()
            deadline += period + (adjust() if adjust is not None else 0)
            overrun = t1 > deadline
            timer.add(t1 - t0, overrun=overrun)
            if stop:
                break
            if status is not None and t1 >= next_status:
                next_status = t1 + int(status_every_s * 1e9)
                s = timer.summary()
                extra = f" {describe()}" if describe else ""
                status.write(
                    f"\r{progress(k + 1, cycles, t1 - start)} mean {s.mean_us:.1f} us p99 {s.p99_us:.1f} us "
                    f"max {s.max_us:.1f} us overruns {s.overruns}{extra}   "
                )
                status.flush()
            if overrun:
                behind = (t1 - deadline) // period
                deadline += behind * period  # skip deadlines we can no longer meet
                continue
            if source is not None:
                sleep_until(source, deadline, 0 if is_virtual(source) else SPIN_NS)
            else:
                wait_until(deadline, now, sleep)
    if status is not None:
        status.write("\n")
        status.flush()
    return timer


def progress(done: int, total: int, elapsed_ns: int, what: str = "cycle") -> str:
    """``cycle 1200/10000 (12%) 998/s 8.8 s left``: where a long run is and when it ends."""
    rate = done / (elapsed_ns / 1e9) if elapsed_ns > 0 else 0.0
    left = (total - done) / rate if rate > 0 else float("inf")
    when = f"{left:.1f} s" if left < 120 else f"{left / 60:.1f} min"
    return f"{what} {done}/{total} ({100 * done // max(total, 1)}%) {rate:.0f}/s {when} left"


def default_status_stream(enabled: bool) -> TextIO | None:
    """stderr when ``enabled`` and it is a terminal, else None."""
    return sys.stderr if enabled and sys.stderr.isatty() else None
