"""Raw-CAN motor faults: a family's error code watched per motor, each onset counted, kept and queued as an event.

A motor's error code (as its family reads it: ``(code, name)``, the name None for a code in the family's
``ok_codes``) that changes to a fault code is one fault onset: counted in :attr:`FaultWatch.count`, kept
in :attr:`FaultWatch.faults` (the newest :data:`FAULT_LOG`) and queued for :meth:`FaultWatch.take`, which
the network calls every cycle: a :class:`MotorFaultEvent` per onset, once. Sans I/O.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from fieldbus.core.drivefault import DriveFault

FAULT_LOG = 100  # motor faults kept per backend (oldest dropped; the count counts them all)


@dataclass(frozen=True)
class MotorFault:
    """A motor reported an error code outside the family's ``ok_codes``: which, when (cycle count) and its name."""

    cycle: int
    slave: str
    code: int
    name: str

    def __str__(self) -> str:
        return f"{self.slave}: motor error 0x{self.code:X} {self.name}"


@dataclass(frozen=True)
class MotorFaultEvent(DriveFault):
    """A raw-CAN motor fault as a cycle event (``CycleResult.events``, recordings): the onset of a family's
    error code outside its ``ok_codes`` (a new error), with the family's name for it.

    ``code`` is the family's own code (an error nibble, a family's error bits), not a CiA 402 0x603F.
    """

    reason: str = ""  # the family's name of ``code`` ("overload", "MOTOR_OVER_TEMP", ...)

    @property
    def name(self) -> str:
        return self.reason

    def __str__(self) -> str:
        return f"{self.slave} ({self.group}[{self.axis}]): motor fault 0x{self.code or 0:X} {self.reason}"


_NO_EVENTS: tuple[MotorFaultEvent, ...] = ()


@dataclass(frozen=True)
class MotorPlace:
    """Where a motor is: its slave name, its group's name and its row (axis) there."""

    slave: str
    group: str
    axis: int


class FaultWatch:
    """The error codes of a bus's motors (``places[i]``: motor ``i``) and their fault onsets."""

    def __init__(self, places: Sequence[MotorPlace]) -> None:
        self.places = list(places)
        self.codes: npt.NDArray[np.int64] = np.zeros(len(places), dtype=np.int64)  # last code per motor
        self.count = 0  # onsets since open, ever (the kept list is bounded)
        self.faults: deque[MotorFault] = deque(maxlen=FAULT_LOG)  # newest last
        self._onsets: deque[tuple[int, int, str]] = deque(maxlen=FAULT_LOG)  # (motor, code, name) not taken

    def seen(self, i: int, err: tuple[int, str | None] | None, cycle: int) -> None:
        """Motor ``i``'s code as its family reads it (None: no code) in cycle count ``cycle``: a new fault
        code is one onset."""
        if err is not None and err[0] != self.codes[i]:
            if err[1] is not None:
                self.count += 1
                self.faults.append(MotorFault(cycle, self.places[i].slave, err[0], err[1]))
                self._onsets.append((i, err[0], err[1]))
            self.codes[i] = err[0]

    def take(self, cycle: int) -> tuple[MotorFaultEvent, ...]:
        """The onsets since the last call as events of cycle ``cycle``, each once; an empty tuple (no
        allocation) mostly."""
        if not self._onsets:
            return _NO_EVENTS
        out = []
        while self._onsets:
            i, code, name = self._onsets.popleft()
            p = self.places[i]
            out.append(MotorFaultEvent(cycle, p.group, p.axis, p.slave, code, name))
        return tuple(out)
