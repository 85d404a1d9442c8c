"""Modes of operation by SDO, for a drive map without 0x6060/0x6061 in its PDOs (one step per cycle).

:class:`AcyclicModes` stands in for the two missing channels: a
:class:`~fieldbus.core.cia402.Cia402Controller` writes its mode requests into
:attr:`AcyclicModes.request` (as it would into ``modes_of_operation``, master
output) and compares :attr:`AcyclicModes.display` (as ``modes_of_operation_display``,
master input). :meth:`AcyclicModes.step`, once per cycle, turns a changed
request into an SDO download of 0x6060 and then reads 0x6061 back by SDO until
it matches. Every transfer is queued on the network's in-OP acyclic channel
(``Operational.submit_sdo_write`` / ``submit_sdo_read``: served by the cycle,
one bounded step per cycle) and only its future is polled: the cycle never waits.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from concurrent.futures import Future
from typing import Any

import numpy as np
import numpy.typing as npt

from fieldbus.errors import FieldbusError

MODES_OF_OPERATION = 0x6060  # INTEGER8, master -> drive
MODES_DISPLAY = 0x6061  # INTEGER8, drive -> master
UNKNOWN_MODE = -128  # display not read yet (no CiA 402 mode has this value)

Submit = Callable[[str, int, int, bytes | None], "Future[bytes | None]"]


class AcyclicModeError(FieldbusError):
    """An SDO transfer of 0x6060/0x6061 failed (the axis, the object and why)."""


class AcyclicModes:
    """0x6060 written and 0x6061 read by SDO for the axes of one group; see the module docstring.

    ``targets``: per axis (row), the slave's name and its 0x6060 index (+0x800
    per axis of a multi-axis slave). ``submit(slave, index, sub_index, data)``
    queues an SDO download (``data`` bytes) or upload (``data`` None) and
    returns its future. ``recoveries()``: how many recoveries the bus has
    completed so far (a rise forgets every display). :meth:`for_group` builds
    all three from a running network.
    """

    def __init__(
        self,
        targets: Sequence[tuple[str, int]],
        submit: Submit,
        recoveries: Callable[[], int] | None = None,
    ) -> None:
        n = len(targets)
        self.targets = tuple(targets)
        self.request: npt.NDArray[np.int8] = np.zeros(n, dtype=np.int8)  # what the controller asks for
        self.display: npt.NDArray[np.int8] = np.full(n, UNKNOWN_MODE, dtype=np.int8)  # 0x6061 as last read
        self.writes: npt.NDArray[np.int64] = np.zeros(n, dtype=np.int64)  # SDO downloads of 0x6060 sent
        self.reads: npt.NDArray[np.int64] = np.zeros(n, dtype=np.int64)  # SDO uploads of 0x6061 sent
        self._submit = submit
        self._written = np.full(n, UNKNOWN_MODE, dtype=np.int8)  # last value downloaded to 0x6060
        self._pending: list[Future[bytes | None] | None] = [None] * n
        self._reading = [False] * n  # the pending transfer is a 0x6061 upload (else a 0x6060 download)
        self._busy = 0
        self._differs = np.zeros(n, dtype=bool)
        self._differs2 = np.zeros(n, dtype=bool)
        self._recoveries = recoveries
        self._recoveries_seen = recoveries() if recoveries is not None else 0
        self.forgotten: npt.NDArray[np.int64] = np.zeros(n, dtype=np.int64)  # displays forgotten per axis
        self._generation = np.zeros(n, dtype=np.int64)  # bumped by forget(): older transfers count no more
        self._sent_generation = np.zeros(n, dtype=np.int64)
        self._recheck = np.zeros(n, dtype=bool)  # the next read decides whether 0x6060 is written again

    @classmethod
    def for_group(cls, op: Any, group: str) -> AcyclicModes:
        """For the group ``group`` of the running network ``op`` (a ``fieldbus.Operational``)."""
        g = op.groups[group]
        names = [s.name for s in g.slaves]
        view = next(v for v in op.buses if names[0] in v.slaves)
        bus = view.name
        backend = view.backend
        axes = g.image.n_axes // len(g.slaves)
        targets = [
            (names[i // axes], g.slaves[i // axes].map.axis_index(MODES_OF_OPERATION, i % axes))
            for i in range(g.image.n_axes)
        ]

        def submit(slave: str, index: int, sub_index: int, data: bytes | None) -> Future[bytes | None]:
            if data is None:
                f: Future[bytes | None] = op.submit_sdo_read(bus, slave, index, sub_index)
                return f
            w: Future[bytes | None] = op.submit_sdo_write(bus, slave, index, sub_index, data)
            return w

        return cls(targets, submit, lambda: int(backend.recoveries))

    @property
    def settled(self) -> bool:
        """Every axis's display shows its request and no transfer is pending."""
        return self._busy == 0 and bool(np.array_equal(self.request, self.display))

    def forget(self, axes: npt.NDArray[np.bool_]) -> None:
        """Forget the display of ``axes`` (a mask): read 0x6061 again, write 0x6060 again if it differs.

        Called for a recovery (see the module docstring); a transfer already in
        flight for such an axis counts no more (its answer may predate the recovery).
        """
        self.display[axes] = UNKNOWN_MODE
        self._recheck[axes] = True
        self._generation[axes] += 1
        self.forgotten[axes] += 1

    def forget_recovered(self) -> None:
        """Forget every display when the bus completed a recovery since the last call (else nothing)."""
        if self._recoveries is None:
            return
        done = self._recoveries()
        if done != self._recoveries_seen:  # rare path: a slave came back, maybe in another mode
            self._recoveries_seen = done
            self.forget(np.ones(len(self.targets), dtype=bool))

    def step(self) -> None:
        """One cycle: poll the pending transfers, queue the next (never waits; no allocation when settled).

        Per axis: a finished download is followed by an upload of 0x6061; an upload
        that does not show the request yet is asked again next cycle. A recovery
        of the bus forgets the displays (:meth:`forget_recovered`). A failed
        transfer raises :class:`AcyclicModeError` naming the axis and object
        (one that a recovery made obsolete is just asked again).
        """
        self.forget_recovered()
        np.not_equal(self.request, self._written, out=self._differs)
        np.not_equal(self.request, self.display, out=self._differs2)
        np.logical_or(self._differs, self._differs2, out=self._differs)
        if self._busy == 0 and not self._differs.any():
            return
        for i in range(len(self.targets)):
            f = self._pending[i]
            if f is not None:
                if not f.done():
                    continue
                self._pending[i] = None
                self._busy -= 1
                self._finish(i, f)
            want = int(self.request[i])
            if want == int(self._written[i]) == int(self.display[i]):  # settled (or just now)
                continue
            slave, index = self.targets[i]
            if want != int(self._written[i]):
                self._pending[i] = self._submit(slave, index, 0, want.to_bytes(1, "little", signed=True))
                self._reading[i] = False
                self._sent_generation[i] = self._generation[i]
                self._written[i] = want
                self.writes[i] += 1
            else:
                self._pending[i] = self._submit(slave, index + 1, 0, None)  # 0x6061 (+0x800 per axis)
                self._reading[i] = True
                self._sent_generation[i] = self._generation[i]
                self.reads[i] += 1
            self._busy += 1

    def _finish(self, i: int, f: Future[bytes | None]) -> None:
        slave, index = self.targets[i]
        obj = index + 1 if self._reading[i] else index
        obsolete = self._sent_generation[i] != self._generation[i]  # asked before a recovery
        try:
            data = f.result()
        except Exception as exc:
            self._written[i] = UNKNOWN_MODE  # write it again on the next request
            if obsolete:
                return
            raise AcyclicModeError(f"{slave} (row {i}): SDO 0x{obj:04X} failed: {exc}") from exc
        if self._reading[i] and not obsolete:
            if not data:
                raise AcyclicModeError(f"{slave} (row {i}): SDO 0x{obj:04X} answered no data")
            self.display[i] = int.from_bytes(data[:1], "little", signed=True)
            if self._recheck[i]:  # the first read after a recovery: the drive's own mode
                self._recheck[i] = False
                if self.display[i] != self.request[i]:
                    self._written[i] = UNKNOWN_MODE  # e.g. its start-up SDO's mode: write ours again
