"""Drive faults as events (pure): every CiA 402 axis that enters FAULT is counted and named.

Invariant S7 of ``docs/safety.md``. Each cycle :class:`DriveFaultWatch` looks
at the statuswords of the rows that are fresh (master inputs); a rising edge
of the fault bit (statusword bit 3: FAULT REACTION ACTIVE or FAULT) is one
:class:`DriveFault` with the drive's error code 0x603F when the map has it in
a PDO (``code`` None otherwise: the network then reads it acyclically). Stale
rows are not judged: their statusword is the last accepted one.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from fieldbus.core.emcy import emcy_name
from fieldbus.core.pdo.image import ProcessImage

STATUSWORD = 0x6041
ERROR_CODE = 0x603F
FAULT_BIT = 0x0008  # statusword bit 3


@dataclass(frozen=True)
class DriveFault:
    """A drive entered FAULT: where, when (cycle index) and its error code (0x603F) by name."""

    cycle: int
    group: str
    axis: int  # row in the group's image
    slave: str
    code: int | None  # 0x603F; None: not in the PDOs (read acyclically when the bus allows)
    slave_axis: int = 0  # axis of a multi-axis slave (0-based): its objects sit 0x800 x this higher

    @property
    def name(self) -> str:
        return emcy_name(self.code) if self.code is not None else "error code not read yet"

    def __str__(self) -> str:
        code = f"0x{self.code:04X} {self.name}" if self.code is not None else self.name
        axis = f" axis {self.slave_axis + 1}" if self.slave_axis else ""
        return f"{self.slave}{axis} ({self.group}[{self.axis}]): drive fault {code}"


_NONE: tuple[DriveFault, ...] = ()


class DriveFaultWatch:
    """Counts fault edges per axis of one group; :meth:`step` returns the new ones (an empty tuple mostly)."""

    def __init__(self, group: str, image: ProcessImage, slaves: tuple[str, ...]) -> None:
        """``slaves``: the group's slaves in row order; a slave with n axes fills n consecutive rows."""
        inputs = image.inputs.layout
        sw = inputs.find(STATUSWORD)
        ec = inputs.find(ERROR_CODE)
        self.group = group
        self.slaves = slaves
        self.active = sw is not None and not sw.channel.scaled
        self._sw: npt.NDArray[np.uint16] | None = image.inputs[sw.name] if self.active and sw else None
        self._code: npt.NDArray[np.uint16] | None = (
            image.inputs[ec.name] if ec is not None and not ec.channel.scaled else None
        )
        n = image.n_axes
        self.axes = n // max(1, len(slaves))  # rows per slave
        self._fresh = np.zeros(n, dtype=bool)  # per row, from the per-slave freshness of a multi-axis group
        self.faults: npt.NDArray[np.int64] = np.zeros(n, dtype=np.int64)  # fault edges per axis since start
        self.in_fault: npt.NDArray[np.bool_] = np.zeros(n, dtype=bool)
        self._now = np.zeros(n, dtype=bool)
        self._edge = np.zeros(n, dtype=bool)
        self._bits = np.zeros(n, dtype=np.uint16)

    def step(self, fresh: npt.NDArray[np.bool_], cycle: int) -> tuple[DriveFault, ...]:
        """Judge the fresh rows of this cycle; the faults that began now (allocation-free when none)."""
        if self._sw is None:
            return _NONE
        if self.axes > 1:  # ``fresh`` per slave: each of its axes' rows
            np.copyto(self._fresh.reshape(-1, self.axes), fresh.reshape(-1, 1))
            fresh = self._fresh
        np.bitwise_and(self._sw, FAULT_BIT, out=self._bits)
        np.not_equal(self._bits, 0, out=self._now)
        np.logical_and(self._now, fresh, out=self._edge)
        np.greater(self._edge, self.in_fault, out=self._edge)  # fresh, in fault now, not before
        np.copyto(self.in_fault, self._now, where=fresh)
        if not self._edge.any():
            return _NONE
        self.faults += self._edge
        rows = np.flatnonzero(self._edge)
        return tuple(
            DriveFault(
                cycle,
                self.group,
                int(i),
                self.slaves[i // self.axes],
                int(self._code[i]) if self._code is not None else None,
                int(i) % self.axes,
            )
            for i in rows
        )
