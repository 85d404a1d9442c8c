"""The raw-CAN backend's pieces out of the transport, alone and sans I/O: the request runner
(fieldbus.core.canrequests) driven by a scripted link on a virtual clock, the per-bus reply router
(fieldbus.core.canroute), the motor-fault watch (fieldbus.core.motorfaults); and the backend itself
pinned to transport only (under 500 lines, no family named in it).

Our own runner against a scripted bus: no independent oracle here (the families' oracle tests,
tests/interop/test_damiao_oracle.py and test_odrive_oracle.py, run the whole path).
"""

from __future__ import annotations

import re
from collections.abc import Generator, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from fieldbus.core.canfamily import Frame, Request
from fieldbus.core.canrequests import ENTER_TIMEOUT_S, Answer, run_bring_up, run_requests
from fieldbus.core.canroute import EXTRA, LATE, ReplyRouter
from fieldbus.core.motorfaults import FaultWatch, MotorPlace

ROOT = Path(__file__).resolve().parents[2]
REPLY_BASE = 0x100  # the scripted motors reply on 0x100 + motor


class ScriptedLink:
    """A bus whose frames arrive at scripted virtual times (s); replies on ``REPLY_BASE + motor`` set
    ``arrived[motor]``, every frame sent is kept."""

    def __init__(self, arrived: Any, script: Sequence[tuple[float, Frame]] = ()) -> None:
        self.t = 0.0
        self.arrived = arrived
        self.queue = sorted(script, key=lambda x: x[0])
        self.sent: list[Frame] = []
        self.taken: list[Frame] = []
        self.drains = 0

    def now(self) -> float:
        return self.t

    def drain(self) -> None:
        self.drains += 1

    def send(self, frame: Frame) -> None:
        self.sent.append(frame)

    def receive(self, timeout_s: float, answer: Answer | None) -> bytes | None:
        if not self.queue or self.queue[0][0] > self.t + timeout_s:
            self.t += timeout_s
            return None
        at, frame = self.queue.pop(0)
        self.t = max(self.t, at)
        if answer is not None and answer(*frame):
            return frame[2]
        self.taken.append(frame)
        if REPLY_BASE <= frame[0] < REPLY_BASE + self.arrived.size:
            self.arrived[frame[0] - REPLY_BASE] = True
        return None


def _answer_to(can_id: int) -> Answer:
    return lambda i, ext, data: i == can_id and not ext


def test_a_transaction_gets_each_answer_back_and_returns_its_result() -> None:
    arrived = np.zeros(2, dtype=bool)
    link = ScriptedLink(arrived, [(0.001, (0x7FF, False, b"\x01")), (0.002, (0x20, False, b"\x2a"))])

    def steps() -> Generator[Request, bytes | None, int]:
        got = yield Request((0x10, False, b"\x33"), answer=_answer_to(0x20))
        assert got is not None
        again = yield Request((0x11, False, bytes(got)), answer=_answer_to(0x21))
        return 0 if again is None else again[0]

    link.queue.append((0.003, (0x21, False, b"\x07")))
    out = run_requests(steps(), link, arrived, link.now)
    assert out.missing == [] and out.request is None and out.result == 7
    assert link.sent == [(0x10, False, b"\x33"), (0x11, False, b"\x2a")]  # the answer's data sent back
    assert link.taken == [(0x7FF, False, b"\x01")]  # a frame answering nothing: taken in as ever
    assert link.drains == 2  # drained before each request


def test_an_unanswered_step_ends_the_run_at_its_time_out_without_resuming() -> None:
    arrived = np.zeros(1, dtype=bool)
    link = ScriptedLink(arrived, [(ENTER_TIMEOUT_S + 1.0, (0x20, False, b""))])  # too late
    resumed: list[bytes | None] = []

    def steps() -> Generator[Request, bytes | None, None]:
        resumed.append((yield Request((0x10, False, b""), awaits=(0,), answer=_answer_to(0x20))))

    out = run_requests(steps(), link, arrived, link.now)
    assert out.missing == [0] and out.request is not None and out.result is None
    assert resumed == [] and link.t == pytest.approx(ENTER_TIMEOUT_S)


def test_awaited_replies_are_cleared_before_sending_and_the_silent_motor_is_blamed() -> None:
    arrived = np.ones(2, dtype=bool)  # stale flags from an earlier cycle must not count
    link = ScriptedLink(arrived, [(0.001, (REPLY_BASE, False, b""))])
    out = run_requests([Request((0x10, False, b""), awaits=(0, 1), timeout_s=0.01)], link, arrived, link.now)
    assert out.missing == [1] and link.t == pytest.approx(0.01)


def test_a_condition_is_awaited_instead_of_a_reply() -> None:
    arrived = np.zeros(1, dtype=bool)
    link = ScriptedLink(arrived, [(0.004, (REPLY_BASE, False, b""))])
    req = Request((0x10, False, b""), awaits=(0,), until=lambda: len(link.taken) > 0, timeout_s=0.05)
    assert run_requests([req, Request((0x12, False, b""))], link, arrived, link.now).missing == []
    assert link.t == pytest.approx(0.004) and len(link.sent) == 2
    never = Request((0x10, False, b""), awaits=(0,), until=lambda: False, timeout_s=0.02, what="closed loop")
    out = run_requests([never], link, arrived, link.now)
    assert out.missing == [0] and out.request is never


class _Family:
    """A family as the router and the bring-up see it: motor m's reply on 0x100 + m, status on 0x700 + m."""

    def __init__(self, motors: Sequence[int], deadline: float | None = None, requests: Any = ()) -> None:
        self.motors = {m: m for m in motors}
        self.deadline = deadline
        self.requests = list(requests)
        self.routed: list[int] = []

    def carries(self, can_id: int, extended: bool, data: bytes) -> Sequence[int]:
        m = can_id - REPLY_BASE
        return (m,) if m in self.motors and not extended else ()

    def route(self, can_id: int, extended: bool, data: bytes) -> Sequence[int]:
        self.routed.append(can_id - REPLY_BASE)
        return self.carries(can_id, extended, data)

    def take(self, can_id: int, extended: bool, data: bytes) -> Sequence[int]:
        m = can_id - 0x700
        return (m,) if m in self.motors else ()

    def deadline_s(self, motor: int) -> float | None:
        return self.deadline

    def bring_up(self, which: str) -> list[Request]:
        return self.requests


def test_bring_up_sends_every_familys_requests_together_then_awaits_them() -> None:
    arrived = np.zeros(3, dtype=bool)
    a = _Family(
        [0, 1],
        requests=[Request((0x10, False, b"\xfc"), awaits=(0,)), Request((0x11, False, b"\xfc"), awaits=(1,))],
    )
    b = _Family([2], requests=[Request((0x12, False, b"\x01"))])  # declarative: no answer awaited
    link = ScriptedLink(arrived, [(0.01, (REPLY_BASE, False, b""))])
    missing, unmet = run_bring_up([a, b], "enter", link, arrived, link.now)  # type: ignore[list-item]
    assert [f[0] for f in link.sent] == [0x10, 0x11, 0x12] and link.drains == 1
    assert missing == [1] and unmet == {} and link.t == pytest.approx(ENTER_TIMEOUT_S)
    assert arrived.tolist() == [True, False, True]


def test_the_router_counts_a_second_reply_extra_and_one_past_its_deadline_late() -> None:
    checked: list[int] = []
    fam = _Family([0, 1], deadline=0.002)
    router = ReplyRouter([fam], 2, lambda i, f: checked.append(i))  # type: ignore[list-item]
    t = [0.0]
    router.sent_at = 0.0
    assert router.wait_until(1.0) == pytest.approx(0.002)  # every motor has a deadline: the last one
    t[0] = 0.001
    assert router.reply(REPLY_BASE, False, b"", lambda: t[0], copy=True) == 1 and fam.routed == [0]
    assert router.reply(REPLY_BASE, False, b"", lambda: t[0], copy=True) == EXTRA
    t[0] = 0.003
    assert router.reply(REPLY_BASE + 1, False, b"", lambda: t[0], copy=True) == LATE  # inputs held
    assert router.arrived.tolist() == [True, False] and fam.routed == [0]
    assert router.reply(0x701, False, b"", lambda: t[0], copy=True) == 0 and checked == [1]  # a status
    assert router.reply(0x123, True, b"", lambda: t[0], copy=True) == 0  # nobody's
    assert (
        router.drained(REPLY_BASE, False, b"") == EXTRA and router.drained(REPLY_BASE + 1, False, b"") == LATE
    )
    assert router.drained(0x700, False, b"") == 0 and checked == [1, 0]


def test_without_deadlines_the_receive_time_out_stands_and_no_reply_is_late() -> None:
    router = ReplyRouter([_Family([0])], 1, lambda i, f: None)  # type: ignore[list-item]
    router.sent_at = 0.0
    assert router.wait_until(0.5) == 0.5
    assert router.reply(REPLY_BASE, False, b"", lambda: 100.0, copy=True) == 1


def test_a_fault_onset_is_counted_kept_and_an_event_once() -> None:
    watch = FaultWatch([MotorPlace("j1", "legs", 0), MotorPlace("j2", "legs", 1)])
    watch.seen(1, (0x1, None), 3)  # a state code (in ok_codes): no fault
    watch.seen(1, (0xE, "overload"), 4)
    watch.seen(1, (0xE, "overload"), 5)  # the same code again: no new onset
    watch.seen(0, None, 5)  # no code read
    assert watch.count == 1 and str(watch.faults[-1]) == "j2: motor error 0xE overload"
    (event,) = watch.take(9)
    assert (event.cycle, event.group, event.axis, event.slave, event.code, event.name) == (
        9,
        "legs",
        1,
        "j2",
        0xE,
        "overload",
    )
    assert watch.take(10) == ()


def test_the_raw_can_backend_is_transport_only() -> None:
    source = (ROOT / "fieldbus" / "backends" / "rawcan.py").read_text(encoding="utf-8")
    assert len(source.splitlines()) < 500
    named = re.findall(r"\bmit\b|damiao|odrive|cubemars|canframes|``frames``|[\"']frames[\"']", source, re.I)
    assert named == []
