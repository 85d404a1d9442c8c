"""The exchange() phase timer (counted, not timed), and what the cycle of a lost EtherCAT frame sends."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from fieldbus.commands.demo import demo_network
from fieldbus.network import Operational, open_network
from fieldbus.platform.phases import PHASES, PhaseTimer


class CountingTimer(PhaseTimer):
    """A phase timer that also keeps the order of its marks."""

    __slots__ = ("marks",)

    def __init__(self) -> None:
        super().__init__()
        self.marks: list[str] = []

    def mark(self, phase: int) -> None:
        self.marks.append(PHASES[phase])
        super().mark(phase)


@pytest.fixture
def op(tmp_path: Path) -> Iterator[Operational]:
    """Two demo joints on the in-process EtherCAT emulator, in OP."""
    with (
        demo_network("sim", 2, 1000.0, tmp_path) as setup,
        open_network(setup.net_file, backend="sim") as net,
    ):
        yield net.bring_up()


def test_every_phase_is_marked_in_order_and_they_add_up_to_the_exchange(op: Operational) -> None:
    assert op.phases is None  # off by default
    timer = CountingTimer()
    op.phases = timer
    for _ in range(5):
        timer.marks.clear()
        res = op.exchange()
        assert timer.marks == [
            "encode",
            "send",
            "wait",
            "judge",
            "accept",
            "contract",
            "acyclic",
            "observers",
        ]
        assert all(ns >= 0 for ns in timer.last_ns)
        # the phases cover exchange() from its start; exchange_ns is read just before the last mark
        assert sum(timer.last_ns) >= res.exchange_ns > 0
        assert set(timer.last_us()) == set(PHASES)


def test_no_mark_when_the_timer_is_taken_away(op: Operational) -> None:
    timer = CountingTimer()
    op.phases = timer
    op.exchange()
    assert timer.marks
    op.phases = None
    timer.marks.clear()
    for _ in range(3):
        op.exchange()
    assert timer.marks == []


def test_a_lost_frame_sends_nothing_more_in_its_cycle_on_the_in_process_chain(op: Operational) -> None:
    """The ethercat backend on the emulated chain (the same recovery code as over veth): the cycle whose
    process-data frame is dropped reaches the chain with its LRW only, the next one too (its full WKC
    ends the recovery); two losses in a row send the recovery's BRD in the second. Counted by the
    chain's own frame counter; the phases say where the contract's work went (not timed)."""
    backend: Any = op.network.backends[0]
    chain = backend.chain
    status = op.result.buses[0]
    for _ in range(5):
        op.exchange()
    for _ in range(3):
        before = chain.frames
        chain.drop_frames(1, process_data=True)
        op.exchange()
        assert status.verdict.name == "TIMEOUT" and status.recovering, status
        assert chain.frames - before == 1  # the LRW, lost; no BRD
        op.exchange()
        assert status.verdict.name == "OK" and not status.recovering, status
        assert chain.frames - before == 2
    before = chain.frames
    chain.drop_frames(2, process_data=True)
    op.exchange()
    op.exchange()
    assert chain.frames - before == 3  # LRW, LRW + the pass's BRD
    assert status.recovering
    for _ in range(3):
        op.exchange()
    assert op.result.fresh and not status.recovering, status
