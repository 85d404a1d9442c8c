"""Virtual time: run_cycles on a VirtualClock, watchers stepping through time, sleep_until."""

from __future__ import annotations

from fieldbus import run_cycles
from fieldbus.platform.clock import VirtualClock, WallClock, sleep_until


def test_run_cycles_on_a_virtual_clock_jumps_to_each_deadline() -> None:
    clock = VirtualClock(start_ns=5)
    seen: list[int] = []

    def step(k: int) -> None:
        seen.append(clock.now_ns())
        if k == 3:
            clock.advance(2_500_000)  # this cycle's work takes 2.5 periods: the next starts at once

    timer = run_cycles(step, 1000, 8, clock=clock)
    # then the schedule is kept: the missed deadline is skipped, no catch-up burst
    assert seen == [5, 1_000_005, 2_000_005, 3_000_005, 5_500_005, 6_000_005, 7_000_005, 8_000_005]
    assert timer.summary().overruns == 1
    assert clock.now_ns() == 9_000_005  # the wait after the last cycle, nothing more


def test_watchers_see_time_pass_in_steps_and_in_order() -> None:
    clock = VirtualClock(step_ns=1_000_000)
    calls: list[tuple[str, int]] = []
    clock.watch(lambda t: calls.append(("a", t)))
    clock.watch(lambda t: calls.append(("b", t)))
    clock.sleep(0.0025)
    steps = [1_000_000, 2_000_000, 2_500_000]
    assert calls == [(name, t) for t in steps for name in ("a", "b")]


def test_a_watcher_that_waits_does_not_call_the_watchers_again() -> None:
    clock = VirtualClock()
    depth: list[int] = []

    def waits(t: int) -> None:
        depth.append(t)
        clock.advance(10)  # e.g. an emulator sleeping inside its timer

    clock.watch(waits)
    clock.advance(1_000_000)
    assert depth == [1_000_000] and clock.now_ns() == 1_000_010


def test_sleep_until_on_the_wall_clock_reaches_the_deadline() -> None:
    wall = WallClock()
    deadline = wall.now_ns() + 2_000_000
    sleep_until(wall, deadline, spin_ns=150_000)
    assert wall.now_ns() >= deadline


def test_the_deadline_clock_sleeps_not_spins_and_never_wakes_before_the_deadline() -> None:
    """``DeadlineClock`` (``fieldbus serve``'s wait): an absolute sleep to ``spin_ns`` before the deadline,
    then a spin. ``sleep_until`` returns at or after the deadline, never before, also when a signal
    interrupts the sleep; the process's CPU time over the waits is a small part of them (a busy wait
    would use all of it; the ratio does not depend on the machine's load)."""
    import signal
    import time

    from fieldbus.platform.clock import DeadlineClock, sleep_until

    clock = DeadlineClock(spin_ns=30_000)
    previous = signal.signal(signal.SIGALRM, lambda *_: None)
    waited = cpu = 0
    try:
        for _ in range(20):
            start, cpu0 = clock.now_ns(), time.process_time_ns()
            deadline = start + 2_000_000
            signal.setitimer(signal.ITIMER_REAL, 0.0005)  # a signal in the middle of the sleep
            sleep_until(clock, deadline)
            assert clock.now_ns() >= deadline
            waited += clock.now_ns() - start
            cpu += time.process_time_ns() - cpu0
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, previous)
    assert cpu < 0.3 * waited, (cpu, waited)
