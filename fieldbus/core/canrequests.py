"""Running a CAN family's requests (:class:`~fieldbus.core.canfamily.Request`) to their answers, sans I/O.

A family's transaction (:data:`~fieldbus.core.canfamily.Steps`: configure, a mode switch, a register
access, recovery) is a generator of requests; each is sent, then its answer (``answer``), its motors'
replies (``awaits``) or its condition (``until``) is awaited at most ``timeout_s`` (None: the bring-up
time-out). A step unanswered ends the sequence. The bus is reached through a :class:`Link` only and
time through a clock callable (seconds): the runner never sends, receives or sleeps by itself, so a
scripted link drives it in a test.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from typing import Any, NamedTuple, Protocol

import numpy as np
import numpy.typing as npt

from fieldbus.core.canfamily import CanFamily, Frame, Request

ENTER_TIMEOUT_S = 2.0  # bring-up (outside the cycle): generous, a loaded host schedules the motors late

Answer = Callable[[int, bool, bytes], bool]


class Link(Protocol):
    """The bus as the runner needs it (the raw-CAN backend's transport)."""

    def drain(self) -> None:
        """Drop every frame already queued (counted late or extra)."""

    def send(self, frame: Frame) -> None:
        """Send ``frame`` (data a :class:`~fieldbus.core.canfamily.Remote`: a remote frame)."""

    def receive(self, timeout_s: float, answer: Answer | None) -> bytes | None:
        """Wait at most ``timeout_s`` for one frame: its data when ``answer`` says it answers (routed nowhere),
        else None (the frame, if any, taken in as a reply or status: the ``arrived`` flags updated)."""


class Outcome(NamedTuple):
    """A run's end: the motors that did not answer, the request they did not answer (None: all answered)
    and the generator's result (its ``return`` value; None when a step went unanswered)."""

    missing: list[int]
    request: Request | None
    result: Any


def await_until(link: Link, now: Callable[[], float], deadline: float, done: Callable[[], bool]) -> bool:
    """Take frames in until ``done()`` or the clock reaches ``deadline`` (s); ``done()`` at the end."""
    while not done() and now() < deadline:
        link.receive(max(0.0, deadline - now()), None)
    return done()


def await_answer(link: Link, now: Callable[[], float], req: Request) -> bytes | None:
    """The data of the frame answering ``req`` within its time-out (others taken in as ever), or None."""
    assert req.answer is not None
    deadline = now() + (req.timeout_s if req.timeout_s is not None else ENTER_TIMEOUT_S)
    while (left := deadline - now()) > 0:
        got = link.receive(left, req.answer)
        if got is not None:
            return got
    return None


def run_requests(
    requests: Iterable[Request], link: Link, arrived: npt.NDArray[np.bool_], now: Callable[[], float]
) -> Outcome:
    """Send a family's ``requests`` in order, each one's answer (sent back into a generator), replies
    (``arrived[motor]`` cleared before, set by the link) or condition awaited within its time-out."""
    steps = iter(requests)
    resume = getattr(steps, "send", None)  # a generator takes each answer's data back
    got: bytes | None = None
    while True:
        try:
            req = resume(got) if resume is not None else next(steps)
        except StopIteration as done:
            return Outcome([], None, done.value)
        link.drain()
        for j in req.awaits:
            arrived[j] = False
        link.send(req.frame)
        got = None
        if req.answer is not None:
            got = await_answer(link, now, req)
            if got is None:
                return Outcome(list(req.awaits), req, None)
            continue
        if not req.awaits and req.until is None:
            continue

        def answered(r: Request = req) -> bool:
            return r.until() if r.until is not None else all(arrived[j] for j in r.awaits)

        deadline = now() + (req.timeout_s if req.timeout_s is not None else ENTER_TIMEOUT_S)
        if not await_until(link, now, deadline, answered):
            return Outcome([j for j in req.awaits if req.until is not None or not arrived[j]], req, None)


def run_bring_up(
    families: Iterable[CanFamily],
    which: str,
    link: Link,
    arrived: npt.NDArray[np.bool_],
    now: Callable[[], float],
) -> tuple[list[int], dict[int, str]]:
    """Send every family's ``bring_up(which)`` requests together (``enter``, ``exit``, ``zero``, ``clear``),
    then await their replies (``awaits``) and conditions (``until``) within the longest time-out.
    ``(the motors that did not answer or meet their condition, motor -> the condition it did not meet)``."""
    link.drain()
    conditions: list[Request] = []  # requests whose condition is awaited (not a reply)
    awaited: set[int] = set()
    for fam in families:  # declarative families: patterns, no answer awaited
        for req in list(fam.bring_up(which)):
            link.send(req.frame)
            if req.until is not None:
                conditions.append(req)
            else:
                awaited.update(req.awaits)
    for i in range(arrived.size):
        arrived[i] = i not in awaited
    deadline = now() + max([ENTER_TIMEOUT_S, *(r.timeout_s or 0.0 for r in conditions)])

    def met() -> bool:
        return all(r.until() for r in conditions if r.until is not None)

    await_until(link, now, deadline, lambda: bool(arrived.all()) and met())
    unmet = {j: r.what for r in conditions if r.until is not None and not r.until() for j in r.awaits}
    return [i for i in range(arrived.size) if not arrived[i] or i in unmet], unmet
