"""Routing one CAN bus's received frames to its motors, sans I/O: replies, status frames, reply deadlines.

The families of a bus (:mod:`fieldbus.core.canfamily`) say which motors a frame carries
(:meth:`~fieldbus.core.canfamily.CanFamily.carries`) and copy it into their input rows
(:meth:`~fieldbus.core.canfamily.CanFamily.route`); this router keeps which motors answered this cycle
(:attr:`ReplyRouter.arrived`) and each motor's reply deadline (s after the cycle's commands: a reply later
is stale, its motors' inputs held). It returns verdicts; the transport counts them (late, extra frames).
Times are seconds of the caller's clock.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from typing import Any

import numpy as np
import numpy.typing as npt

from fieldbus.core.canfamily import CanFamily, FamilyMotor
from fieldbus.errors import FieldbusError

EXTRA = -1  # a second reply of motors that answered this cycle
LATE = -2  # a reply past its deadline, or one of an earlier cycle (drained): its motors' inputs held

Checked = Callable[[int, CanFamily], None]  # a status changed motor ``i``'s code: check it


def bus_motors(bus: str, slaves: Sequence[tuple[Any, Any, Any]]) -> dict[str, list[FamilyMotor]]:
    """The motors of bus ``bus`` by family name: ``slaves[i]`` is motor ``i``'s (slave, output row, input
    row), the slave's map naming its family. A map without a ``rawcan`` family is refused."""
    declared: dict[str, list[FamilyMotor]] = {}
    for i, (slave, out_row, in_row) in enumerate(slaves):
        cfg = slave.map.rawcan
        if cfg is None or cfg.protocol is None:
            raise FieldbusError(f"bus '{bus}': slave {slave.name} map {slave.map.name} has no rawcan family")
        motor = FamilyMotor(i, slave.node_id or 0, cfg.protocol, out_row, in_row, slave.name)
        declared.setdefault(cfg.family, []).append(motor)
    return declared


class ReplyRouter:
    """The replies of ``n`` motors on one bus, run by ``families`` (each its motors)."""

    def __init__(self, families: Sequence[CanFamily], n: int, checked: Checked) -> None:
        self.families = list(families)
        self.family_of: dict[int, CanFamily] = {i: f for f in self.families for i in f.motors}
        self.arrived: npt.NDArray[np.bool_] = np.zeros(n, dtype=bool)  # answered this cycle
        self._checked = checked
        # a family's reply deadline per motor (s after the cycle's commands; None: the receive time-out)
        self.reply_by: list[float | None] = [None] * n
        for i, fam in self.family_of.items():
            self.reply_by[i] = fam.deadline_s(i)
        by = [d for d in self.reply_by if d is not None]
        self.deadlines = bool(by)
        self.wait_cap = max(by) if len(by) == n else None  # every motor has a deadline: the last one
        self.sent_at: float | None = None  # when this cycle's commands went out (while a deadline counts)

    @classmethod
    def build(
        cls,
        declared: Mapping[str, list[FamilyMotor]],
        registered: Mapping[str, type[CanFamily]],
        n: int,
        checked: Checked,
    ) -> ReplyRouter:
        """One family object per family name of the bus (``declared``: its motors); a family refusing its
        motors raises ValueError."""
        return cls([registered[name](ms) for name, ms in declared.items()], n, checked)

    def wait_until(self, deadline: float) -> float:
        """The cycle's receive deadline (s) capped by the last reply deadline when every motor has one."""
        if self.wait_cap is not None and self.sent_at is not None:
            return min(deadline, self.sent_at + self.wait_cap)
        return deadline

    def carries(self, can_id: int, extended: bool, data: bytes) -> tuple[CanFamily | None, Sequence[int]]:
        """The family whose reply the frame is and the motors it carries (none: ``(None, ())``)."""
        for fam in self.families:
            if motors := fam.carries(can_id, extended, data):
                return fam, motors
        return None, ()

    def reply(self, can_id: int, extended: bool, data: bytes, now: Callable[[], float], *, copy: bool) -> int:
        """A data frame received now (``now()``, read only while a deadline counts): the number of motors it answered for (into their rows when
        ``copy``), :data:`EXTRA`, :data:`LATE`, or 0 (a status frame taken in, or nobody's)."""
        fam, motors = self.carries(can_id, extended, data)
        if fam is None:
            self.take(can_id, extended, data)
            return 0
        if any(self.arrived[i] for i in motors):
            return EXTRA
        if copy and self.sent_at is not None and self.past_deadline(motors, now()):
            return LATE
        if copy:
            motors = fam.route(can_id, extended, data)
        for i in motors:
            self.arrived[i] = True
        return len(motors)

    def drained(self, can_id: int, extended: bool, data: bytes) -> int:
        """A data frame found queued before a cycle: :data:`EXTRA` when its motors answered this cycle,
        :data:`LATE` when not, 0 when it is no reply (a status frame: taken in)."""
        _, motors = self.carries(can_id, extended, data)
        if motors:
            return EXTRA if all(self.arrived[j] for j in motors) else LATE
        self.take(can_id, extended, data)
        return 0

    def past_deadline(self, motors: Sequence[int], now: float) -> bool:
        """A reply of ``motors`` at ``now`` is past the reply deadline of one of them (a shared frame: any)."""
        sent = self.sent_at
        return sent is not None and any(
            (d := self.reply_by[i]) is not None and now > sent + d for i in motors
        )

    def take(self, can_id: int, extended: bool, data: bytes) -> bool:
        """A family's status frame (not a cycle reply) taken in; each motor whose code it may have changed
        is checked at once. False when no family takes it."""
        for fam in self.families:
            if motors := fam.take(can_id, extended, data):
                for i in motors:
                    self._checked(i, fam)
                return True
        return False
