"""Execute an :class:`~fieldbus.core.sdo.SdoPlan` through a backend's SDO verbs.

All writes first, in plan order; then every step with a ``readback`` is read
and compared. The first abort or mismatch stops the plan and raises with the
slave, object and abort code; nothing after it is written.
"""

from __future__ import annotations

from collections.abc import Callable, Generator
from functools import partial
from typing import TypeVar

from fieldbus.core.sdo import SdoPlan, StepKind
from fieldbus.errors import BusTimeoutError, SdoAbortError, SdoMismatchError

Write = Callable[[int, int, bytes], None]
Read = Callable[[int, int, int], bytes]  # (index, sub, expected size) -> bytes
T = TypeVar("T")


def apply_plan(plan: SdoPlan, write: Write, read: Read, *, slave: str) -> int:
    """Run ``plan``; returns the number of SDO transfers made.

    ``write``/``read`` raise :class:`SdoAbortError` on an abort; this adds the
    slave name when the backend did not.
    """
    steps = plan_transfers(plan, write, read, slave=slave)
    while True:
        try:
            next(steps)
        except StopIteration as done:
            return int(done.value)


def plan_transfers(
    plan: SdoPlan, write: Write, read: Read, *, slave: str, tries: int = 1
) -> Generator[None, None, int]:
    """:func:`apply_plan` one transfer at a time: yields after each SDO, returns the count.

    For recovery inside the cycle, where no cycle may wait for a whole plan:
    the backend keeps each transfer's timeout short, and a transfer without
    answer (:class:`BusTimeoutError`) is tried again at the next step, up to
    ``tries`` times in all (an abort or a mismatch ends the plan at once).
    """
    transfers = 0
    try:
        for step in plan.steps:
            if step.kind is StepKind.WRITE:
                yield from retried(partial(write, step.index, step.sub_index, step.data), tries)
                transfers += 1
                yield
        for step in plan.checks:
            assert step.readback is not None
            got = yield from retried(partial(read, step.index, step.sub_index, len(step.readback)), tries)
            transfers += 1
            if got[: len(step.readback)] != step.readback or (
                len(got) > len(step.readback) and any(got[len(step.readback) :])
            ):
                raise SdoMismatchError(
                    index=step.index,
                    sub_index=step.sub_index,
                    expected=step.readback,
                    received=got,
                    slave=slave,
                )
            yield
    except SdoAbortError as exc:
        if not exc.slave:
            raise SdoAbortError(
                exc.code, index=exc.index, sub_index=exc.sub_index, slave=slave, detail=exc.detail
            ) from None
        raise
    return transfers


def retried(
    call: Callable[[], T], tries: int, retry_on: tuple[type[BaseException], ...] = (BusTimeoutError,)
) -> Generator[None, None, T]:
    """``call()``, made again after a step while it raises one of ``retry_on`` (``tries`` calls in all).

    For idempotent transfers inside the cycle: a lost or late answer costs one step, not the whole
    sequence; the last failure is raised.
    """
    for _ in range(tries - 1):
        try:
            return call()
        except retry_on:
            yield
    return call()
