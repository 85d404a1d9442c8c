"""The wire runner keeps its reply path clear: the garbage collector runs in idle gaps, capabilities are read.

The timing figures themselves are wall clock and live in ``benchmarks/emulator_reply.py``
(docs/emulator.md, "Reply time"); these tests check the mechanisms.
"""

from __future__ import annotations

import gc
import os
from collections.abc import Iterator

import pytest

from sim_slaves.ethercat.runner import (
    ANTICIPATE_LATE_NS,
    CAP_IPC_LOCK,
    CAP_SYS_NICE,
    DEFAULT_RT_PRIORITY,
    GC_GEN0,
    AfterReply,
    Anticipator,
    IdleCollector,
    ReplyTimes,
    has_capability,
    reply_timing,
)


@pytest.fixture
def collector() -> Iterator[IdleCollector]:
    c = IdleCollector()
    c.start()
    try:
        yield c
    finally:
        c.stop()


class _Cycle:
    """An object in a reference cycle: garbage only a collection frees."""

    def __init__(self) -> None:
        self.me = self


def test_the_collector_is_off_and_start_up_objects_are_frozen(collector: IdleCollector) -> None:
    assert not gc.isenabled()
    assert gc.get_freeze_count() > 1000  # everything alive at start-up: never scanned again
    before = gc.get_count()[0]
    garbage = [_Cycle() for _ in range(3 * GC_GEN0)]
    del garbage
    assert gc.get_count()[0] >= before + 3 * GC_GEN0  # allocations piled up: no collection ran


def test_a_gap_collects_what_piled_up_and_only_then(collector: IdleCollector) -> None:
    gc.collect()
    assert not collector.gap()  # nothing due: a gap costs nothing
    for _ in range(GC_GEN0 + 10):
        _Cycle()
    assert collector.gap()
    assert gc.get_count()[0] < GC_GEN0 and collector.collections == 1
    assert gc.garbage == []


def test_stop_gives_the_collector_back() -> None:
    was = gc.isenabled()
    c = IdleCollector()
    c.start()
    c.stop()
    assert gc.isenabled() == was and gc.get_freeze_count() == 0


def _can_set_fifo() -> bool:
    """The independent way to know: ask the kernel for SCHED_FIFO and put everything back."""
    old = os.sched_getscheduler(0), os.sched_getparam(0)
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(1))
    except PermissionError:
        return False
    os.sched_setscheduler(0, *old)
    return True


def test_cap_sys_nice_is_read_from_the_effective_set() -> None:
    assert has_capability(CAP_SYS_NICE) == _can_set_fifo()


def test_auto_asks_for_sched_fifo_and_locked_memory_where_the_capabilities_allow() -> None:
    cfg = reply_timing("auto", None, "auto")
    assert cfg.priority == (DEFAULT_RT_PRIORITY if has_capability(CAP_SYS_NICE) else None)
    assert cfg.lock_memory == has_capability(CAP_IPC_LOCK)
    off = reply_timing("off", 1, "off")
    assert (off.priority, off.cpu, off.lock_memory) == (None, 1, False)
    assert reply_timing("70", None, "on").priority == 70


def test_after_a_reply_the_runner_yields_only_at_sched_fifo() -> None:
    """A plain runner goes straight on (a master preempts it anyway); at SCHED_FIFO it waits."""
    assert AfterReply("yield").mode == "hold" or os.sched_getscheduler(0) == os.SCHED_FIFO
    if not has_capability(CAP_SYS_NICE):
        return
    old = os.sched_getscheduler(0), os.sched_getparam(0)
    os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(1))
    try:
        assert AfterReply("yield").mode == "yield" and AfterReply("hold").mode == "hold"
    finally:
        os.sched_setscheduler(0, *old)
    with pytest.raises(ValueError, match="'yield' or 'hold'"):
        AfterReply("plain")


def test_reply_times_count_the_emulator_s_own_part() -> None:
    t = ReplyTimes()
    t.add(1_000_000, 1_030_000, 1_080_000)  # 30 µs to pick up, 80 µs to the reply
    t.add(2_000_000, 3_400_000, 3_500_000)  # 1.5 ms: over 1 ms
    got = t.to_json()
    assert (got["cycles"], got["over_1ms"], got["max"], got["pickup"]["max"]) == (2, 1, 1500.0, 1400.0)
    t.reset()
    assert t.to_json()["cycles"] == 0


def _cycles(a: Anticipator, start_ns: int, period_ns: int, n: int, frames: int = 2) -> int:
    """``n`` cycles of ``frames`` frames 20 µs apart from ``start_ns``; returns the next cycle's start."""
    t = start_ns
    for _ in range(n):
        for k in range(frames):
            a.arrived(t + k * 20_000)
        t += period_ns
    return t


def test_the_runner_expects_a_paced_masters_next_frame_after_steady_cycles() -> None:
    a = Anticipator(200_000)
    t0 = 10**12
    nxt = _cycles(a, t0, 500_000, Anticipator.STEADY + 1)  # the first spacing sets the period
    assert a.due_ns(nxt - 300_000) == 0  # not steady yet
    nxt = _cycles(a, nxt, 500_000, 1)
    assert a.due_ns(nxt - 300_000) == nxt  # the frames of one cycle are one start
    assert a.due_ns(nxt + ANTICIPATE_LATE_NS) == nxt  # still polling for a slightly late master
    assert a.due_ns(nxt + ANTICIPATE_LATE_NS + 1) == 0  # a master that paused: sleep until it sends


def test_a_changed_period_is_learned_again_and_lead_zero_is_off() -> None:
    a = Anticipator(200_000)
    nxt = _cycles(a, 10**12, 500_000, 20)
    nxt = _cycles(a, nxt, 1_000_000, 3)  # the master slowed to 1 kHz
    assert a.due_ns(nxt - 500_000) == 0
    nxt = _cycles(a, nxt, 1_000_000, Anticipator.STEADY)
    assert a.due_ns(nxt - 500_000) == nxt
    off = Anticipator(0)
    nxt = _cycles(off, 10**12, 500_000, 20)
    assert off.due_ns(nxt - 300_000) == 0


def test_a_master_sending_flat_out_is_never_anticipated() -> None:
    a = Anticipator(200_000)
    t = 10**12
    for _ in range(100):  # frames 100 µs apart: one endless cycle
        a.arrived(t)
        t += 100_000
    assert a.due_ns(t) == 0
