"""Execute an :class:`~fieldbus.core.sdo.SdoPlan` through a backend's SDO verbs.

All writes first, in plan order; then every step with a ``readback`` is read
and compared. The first abort or mismatch stops the plan and raises with the
slave, object and abort code; nothing after it is written.
"""

from __future__ import annotations

from collections.abc import Callable, Generator
from functools import partial

from fieldbus.core.sdo import SdoPlan, StepKind
from fieldbus.errors import BusTimeoutError, SdoAbortError, SdoMismatchError

Write = Callable[[int, int, bytes], None]
Read = Callable[[int, int, int], bytes]  # (index, sub, expected size) -> bytes


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
                yield from _answered(partial(write, step.index, step.sub_index, step.data), tries)
                transfers += 1
                yield
        for step in plan.checks:
            assert step.readback is not None
            got = yield from _answered(partial(read, step.index, step.sub_index, len(step.readback)), tries)
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


def _answered(transfer: Callable[[], bytes | None], tries: int) -> Generator[None, None, bytes]:
    """``transfer()``, tried again after a step while it gets no answer (``tries`` in all)."""
    for attempt in range(tries):
        try:
            return transfer() or b""
        except BusTimeoutError:
            if attempt == tries - 1:
                raise
        yield
    raise AssertionError("unreachable")  # pragma: no cover
