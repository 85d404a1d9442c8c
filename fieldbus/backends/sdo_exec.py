"""Execute an :class:`~fieldbus.core.sdo.SdoPlan` through a backend's SDO verbs.

All writes first, in plan order; then every step with a ``readback`` is read
and compared. The first abort or mismatch stops the plan and raises with the
slave, object and abort code; nothing after it is written.
"""

from __future__ import annotations

from collections.abc import Callable, Generator

from fieldbus.core.sdo import SdoPlan, StepKind
from fieldbus.errors import SdoAbortError, SdoMismatchError

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


def plan_transfers(plan: SdoPlan, write: Write, read: Read, *, slave: str) -> Generator[None, None, int]:
    """:func:`apply_plan` one transfer at a time: yields after each SDO, returns the count.

    For recovery inside the cycle, where no cycle may wait for a whole plan.
    """
    transfers = 0
    try:
        for step in plan.steps:
            if step.kind is StepKind.WRITE:
                write(step.index, step.sub_index, step.data)
                transfers += 1
                yield
        for step in plan.checks:
            assert step.readback is not None
            got = read(step.index, step.sub_index, len(step.readback))
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
