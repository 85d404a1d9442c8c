"""The raw-CAN event pump: faults the motors report themselves become events of the cycle.

A raw-CAN motor (a Damiao's error code, an ODrive's axis error) reports its
faults in its own replies; the backend keeps their onsets
(:meth:`~fieldbus.backends.base.Backend.take_motor_events`) and the pump moves
them, once per bus cycle after the inputs were accepted, into the cycle's
events, where observers (a recording, the monitor) get them as
:class:`~fieldbus.core.drivefault.DriveFault` events. Other buses have none
(the base class's default).
"""

from __future__ import annotations

from collections.abc import Sequence

from fieldbus.backends.base import Backend
from fieldbus.cycle.status import CycleEvent


class MotorEventPump:
    """Moves each bus's motor-reported faults into the cycle's events; counts what it moved."""

    def __init__(self, backends: Sequence[Backend]) -> None:
        self.backends = list(backends)
        self.pumped = [0] * len(self.backends)  # events moved per bus since bring-up
        # per bus: its motors can report faults (the backend overrides take_motor_events); else none to pump
        self.reporting = [
            type(b).take_motor_events is not Backend.take_motor_events or "take_motor_events" in vars(b)
            for b in self.backends
        ]

    def pump(self, k: int, cycle: int, events: list[CycleEvent]) -> int:
        """Bus ``k``'s faults reported since the last call, as events of ``cycle``; how many."""
        if not self.reporting[k]:
            return 0
        got = self.backends[k].take_motor_events(cycle)
        if got:
            events.extend(got)
            self.pumped[k] += len(got)
        return len(got)
