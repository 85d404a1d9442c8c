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
    CAP_IPC_LOCK,
    CAP_SYS_NICE,
    DEFAULT_RT_PRIORITY,
    GC_GEN0,
    AfterReply,
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
