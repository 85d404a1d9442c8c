"""A drive's diagnosis history, read through the running cycle and decoded to names.

On CANopen (and CoE drives that keep it) the pre-defined error field 0x1003:
sub 0 the number of errors, then subs 1..n, newest first (CiA 301 7.5.2.3).
The reads go through :meth:`fieldbus.Operational.submit_sdo_read`, so the
cycle serves them one bounded step at a time: call :meth:`ErrorHistory.poll`
once per cycle (after ``exchange()``) until it returns the entries.
"""

from __future__ import annotations

from concurrent.futures import Future
from typing import Protocol

from fieldbus.core.emcy import ErrorEntry, decode_error_field
from fieldbus.errors import FieldbusError

ERROR_FIELD = 0x1003  # CiA 301 pre-defined error field
MAX_ENTRIES = 254  # sub-indexes 1..254


class _SdoReader(Protocol):
    def submit_sdo_read(self, bus: str, slave: str, index: int, sub_index: int) -> Future[bytes | None]: ...


class ErrorHistory:
    """Reads 0x1003 of one slave without blocking the cycle: :meth:`poll` each cycle until not None.

    A failed read (an SDO abort: the drive has no history; a time-out) raises from :meth:`poll`.
    """

    def __init__(self, op: _SdoReader, bus: str, slave: str, *, index: int = ERROR_FIELD) -> None:
        self._op, self.bus, self.slave, self.index = op, bus, slave, index
        self._count: int | None = None
        self._entries: list[ErrorEntry] = []
        self._future = op.submit_sdo_read(bus, slave, index, 0)

    def poll(self) -> list[ErrorEntry] | None:
        """The history, newest first, once every sub-index has been read; None while reads are pending."""
        while self._future.done():
            data = self._future.result()
            if data is None or not data:
                raise FieldbusError(f"{self.bus}/{self.slave}: 0x{self.index:04X} read returned nothing")
            if self._count is None:
                self._count = min(data[0], MAX_ENTRIES)
            else:
                self._entries.append(decode_error_field(data))
            if len(self._entries) >= self._count:
                return list(self._entries)
            self._future = self._op.submit_sdo_read(self.bus, self.slave, self.index, len(self._entries) + 1)
        return None
