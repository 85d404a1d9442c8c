"""Drive faults as events (pure): every CiA 402 axis that enters FAULT is counted and named.

Invariant S7 of ``docs/safety.md``. Each cycle :class:`DriveFaultWatch` looks
at the statuswords of the rows that are fresh (master inputs); a rising edge
of the fault bit (statusword bit 3: FAULT REACTION ACTIVE or FAULT) is one
:class:`DriveFault` with the drive's error code 0x603F when the map has it in
a PDO (``code`` None otherwise: the network then reads it acyclically). Stale
rows are not judged: their statusword is the last accepted one.
"""

from __future__ import annotations

from collections.abc import Callable
from concurrent.futures import Future
from dataclasses import dataclass, field, replace

import numpy as np
import numpy.typing as npt

from fieldbus.core import kernels
from fieldbus.core.diagnosis import DiagMessage, DiagnosisReader
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
    # keyword-only (a subclass's own fields stay positional after ``code``):
    # axis of a multi-axis slave (0-based): its objects sit 0x800 x this higher
    slave_axis: int = field(default=0, kw_only=True)
    # the drive's diagnosis history (EtherCAT 0x10F3, ETG.1020), newest first, when its map asks for it
    # (``ethercat.diagnosis_history``); None: not read
    history: tuple[DiagMessage, ...] | None = field(default=None, kw_only=True)

    @property
    def name(self) -> str:
        return emcy_name(self.code) if self.code is not None else "error code not read yet"

    def __str__(self) -> str:
        code = f"0x{self.code:04X} {self.name}" if self.code is not None else self.name
        axis = f" axis {self.slave_axis + 1}" if self.slave_axis else ""
        text = f"{self.slave}{axis} ({self.group}[{self.axis}]): drive fault {code}"
        if self.history:
            text += f"; diagnosis history: {self.history[0]}"
        return text


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
        self._faulted = False  # an axis of in_fault is set (the clean cycle's test skips the rest without)
        self._now = np.zeros(n, dtype=bool)
        self._edge = np.zeros(n, dtype=bool)
        self._bits = np.zeros(n, dtype=np.uint16)
        # the clean cycle's test, one call (core.kernels): a fault bit set anywhere
        self._fault_bit = kernels.any_bits(self._sw, FAULT_BIT) if self._sw is not None else None

    def step(self, fresh: npt.NDArray[np.bool_], cycle: int) -> tuple[DriveFault, ...]:
        """Judge the fresh rows of this cycle; the faults that began now (allocation-free when none)."""
        if self._sw is None or self._fault_bit is None:
            return _NONE
        if not self._faulted and not self._fault_bit():
            return _NONE  # no fault bit anywhere and no axis in fault: nothing can change (the clean cycle)
        np.bitwise_and(self._sw, FAULT_BIT, out=self._bits)
        if self.axes > 1:  # ``fresh`` per slave: each of its axes' rows
            np.copyto(self._fresh.reshape(-1, self.axes), fresh.reshape(-1, 1))
            fresh = self._fresh
        np.not_equal(self._bits, 0, out=self._now)
        np.logical_and(self._now, fresh, out=self._edge)
        np.greater(self._edge, self.in_fault, out=self._edge)  # fresh, in fault now, not before
        np.copyto(self.in_fault, self._now, where=fresh)
        self._faulted = bool(np.count_nonzero(self.in_fault))
        if not np.count_nonzero(self._edge):
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
                slave_axis=int(i) % self.axes,
            )
            for i in rows
        )


class FaultFollowUp:
    """What a fault's event still lacks, read acyclically: 0x603F when not in a PDO, then 0x10F3.

    ``submit(index, sub_index)`` starts an SDO upload from the faulted slave
    (served by the cycle). :meth:`poll` once per cycle: None while reads are
    pending, then the fault again with its code and history (a failed history
    read leaves ``history`` None and says why in :attr:`error`). ``code_index``
    is the axis's 0x603F (+0x800 per axis), None when the event has the code.
    """

    def __init__(
        self,
        fault: DriveFault,
        submit: Callable[[int, int], Future[bytes | None]],
        *,
        code_index: int | None,
        history: bool,
        last: int = 8,
    ) -> None:
        self.fault = fault
        self.error: str | None = None
        self._submit = submit
        self._history = history
        self._last = last
        self._code: Future[bytes | None] | None = submit(code_index, 0) if code_index is not None else None
        self._reader: DiagnosisReader | None = None
        if self._code is None and history:
            self._reader = DiagnosisReader(submit, last=last)

    @property
    def code_pending(self) -> bool:
        """The 0x603F read has not completed yet (a fault reset now would clear the code it reads)."""
        return self._code is not None

    def poll(self) -> DriveFault | None:
        """The completed fault, or None while a read is pending. A failed 0x603F read raises."""
        if self._code is not None:
            if not self._code.done():
                return None
            data = self._code.result()  # raises when the read failed
            if data is None or len(data) < 2:
                raise ValueError(f"0x603F answered {data!r}")
            self.fault = replace(self.fault, code=int.from_bytes(data[:2], "little"))
            self._code = None
            if self._history:
                self._reader = DiagnosisReader(self._submit, last=self._last)
        if self._reader is not None:
            try:
                messages = self._reader.poll()
            except Exception as exc:  # no history (an abort), a time-out: the fault stands without it
                self.error = f"0x10F3 of {self.fault.slave}: {type(exc).__name__}: {exc}"
                self._reader = None
                return self.fault
            if messages is None:
                return None
            self.fault = replace(self.fault, history=tuple(messages))
            self._reader = None
        return self.fault
