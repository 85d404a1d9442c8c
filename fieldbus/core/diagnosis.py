"""A drive's diagnosis history, read through the running cycle and decoded to names.

On CANopen (and CoE drives that keep it) the pre-defined error field 0x1003:
sub 0 the number of errors, then subs 1..n, newest first (CiA 301 7.5.2.3).
On EtherCAT the diagnosis history 0x10F3 of ETG.1020 ("Protocol Enhancements",
section "Diagnosis history"): sub 1 the maximum number of messages, sub 2 the
sub-index of the newest, sub 3 the newest acknowledged, sub 4 new messages
available, sub 5 flags, subs 6.. the messages in a ring, each a diag code
(UDINT), flags (UINT: severity, local time stamp, number of parameters), a text
id (UINT), a time stamp (ULINT, ns) and the parameters. A diag code whose low
word is 0xE800 carries a CiA 301 / CiA 402 error code in its high word, named
from the same table as 0x603F and EMCY (:class:`DiagnosisHistory`).
The reads go through :meth:`fieldbus.Operational.submit_sdo_read`, so the
cycle serves them one bounded step at a time: call :meth:`ErrorHistory.poll`
once per cycle (after ``exchange()``) until it returns the entries.
"""

from __future__ import annotations

import difflib
import struct
from collections.abc import Callable
from concurrent.futures import Future
from dataclasses import dataclass
from typing import Protocol

from fieldbus.core.emcy import EXACT, ErrorEntry, decode_error_field, emcy_name
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


# -- EtherCAT: the diagnosis history 0x10F3 (ETG.1020) ------------------------------------------------

DIAG_HISTORY = 0x10F3  # ETG.1020 diagnosis history object
DIAG_MAX_MESSAGES = 1  # sub 1: maximum messages (UINT8), how many sub-indexes hold messages
DIAG_NEWEST = 2  # sub 2: newest message (UINT8), the sub-index of the newest one (0: none yet)
DIAG_NEWEST_ACK = 3  # sub 3: newest acknowledged message (UINT8, written by the master)
DIAG_NEW_AVAILABLE = 4  # sub 4: new messages available (BOOL)
DIAG_FLAGS = 5  # sub 5: flags (UINT16)
DIAG_FIRST_MESSAGE = 6  # subs 6 .. 5 + maximum: the messages, a ring
DIAG_EMCY = 0xE800  # diag code low word: its high word is a CiA 301 / CiA 402 emergency error code
DIAG_MESSAGE_HEAD = 16  # diag code UDINT, flags UINT, text id UINT, time stamp ULINT
SEVERITIES = ("info", "warning", "error")
# ETG.1020 parameter data types (the low 12 bits of a parameter's flags word): CoE type code -> bytes
DIAG_PARAM_BYTES = {0x0001: 1, 0x0002: 1, 0x0003: 2, 0x0004: 4, 0x0005: 1, 0x0006: 2, 0x0007: 4}
_SIGNED_PARAMS = (0x0002, 0x0003, 0x0004)


@dataclass(frozen=True)
class DiagMessage:
    """One ETG.1020 diagnosis message (an entry of 0x10F3), decoded.

    ``code`` the 32-bit diag code; ``flags`` bits 0-3 the severity (0 info,
    1 warning, 2 error), bit 4 a local (not DC) time stamp, bits 8-15 the
    number of parameters; ``text_id`` the device's text (from its ESI);
    ``timestamp_ns`` ns (DC system time, or the device's local time);
    ``params`` the parameters, numbers where their type says so.
    """

    code: int
    flags: int
    text_id: int
    timestamp_ns: int
    params: tuple[int | bytes, ...] = ()

    @property
    def severity(self) -> str:
        kind = self.flags & 0x0F
        return SEVERITIES[kind] if kind < len(SEVERITIES) else f"severity {kind}"

    @property
    def local_time(self) -> bool:
        """The time stamp is the device's local clock, not DC system time."""
        return bool(self.flags & 0x10)

    @property
    def emcy_code(self) -> int | None:
        """The CiA 301 / CiA 402 error code of a diag code 0xE800 (in its high word); None otherwise."""
        return self.code >> 16 if self.code & 0xFFFF == DIAG_EMCY else None

    @property
    def name(self) -> str:
        """What happened: the standard error code's name, else the diag code's range (ETG.1020)."""
        low = self.code & 0xFFFF
        emcy = self.emcy_code
        if emcy is not None:
            return emcy_name(emcy)
        if 0xE000 <= low <= 0xE7FF:
            return f"manufacturer diag code 0x{self.code:08X}"
        if 0xEE00 <= low <= 0xEFFF:
            return f"profile diag code 0x{self.code:08X}"
        return f"diag code 0x{self.code:08X}"

    def __str__(self) -> str:
        return f"{self.severity} {self.name} (diag code 0x{self.code:08X}, text {self.text_id}, t {self.timestamp_ns} ns)"


def decode_diag_message(data: bytes) -> DiagMessage:
    """An ETG.1020 diagnosis message (0x10F3 sub 6..) -> :class:`DiagMessage`.

    Each parameter is a UINT16 flags word (bits 12-15: 0 a data type in bits 0-11, 1 a byte array of
    the length in bits 0-11, 2 a string of that length) followed by its value. Raises
    :class:`~fieldbus.errors.FieldbusError` for a message shorter than its fixed part or its parameters.
    """
    if len(data) < DIAG_MESSAGE_HEAD:
        raise FieldbusError(
            f"diagnosis message of {len(data)} bytes: the fixed part alone is {DIAG_MESSAGE_HEAD}"
        )
    code, flags, text_id, stamp = struct.unpack_from("<IHHQ", data)
    params: list[int | bytes] = []
    pos = DIAG_MESSAGE_HEAD
    for k in range(flags >> 8):
        if pos + 2 > len(data):
            raise FieldbusError(f"diagnosis message: parameter {k + 1} of {flags >> 8} is missing")
        (pflags,) = struct.unpack_from("<H", data, pos)
        pos += 2
        kind, low = pflags >> 12, pflags & 0x0FFF
        size = DIAG_PARAM_BYTES.get(low) if kind == 0 else low if kind in (1, 2) else None
        if size is None or pos + size > len(data):
            raise FieldbusError(f"diagnosis message: parameter {k + 1} (flags 0x{pflags:04X}) cannot be read")
        raw = bytes(data[pos : pos + size])
        pos += size
        params.append(int.from_bytes(raw, "little", signed=low in _SIGNED_PARAMS) if kind == 0 else raw)
    return DiagMessage(code, flags, text_id, stamp, tuple(params))


def encode_diag_message(
    code: int,
    timestamp_ns: int,
    params: tuple[tuple[int, int], ...] = (),
    *,
    severity: int = 2,
    local: bool = True,
) -> bytes:
    """An ETG.1020 diagnosis message: ``params`` as (CoE data type, value) pairs (what an emulated device writes)."""
    flags = (severity & 0x0F) | (0x10 if local else 0) | (len(params) << 8)
    out = struct.pack("<IHHQ", code, flags, 0, timestamp_ns & 0xFFFFFFFFFFFFFFFF)
    for dtype, value in params:
        size = DIAG_PARAM_BYTES[dtype]
        out += struct.pack("<H", dtype) + int(value).to_bytes(size, "little", signed=dtype in _SIGNED_PARAMS)
    return out


def emcy_diag_code(error_code: int) -> int:
    """The ETG.1020 diag code of a CiA 301 / CiA 402 error code: the code in the high word, 0xE800 low."""
    return (error_code & 0xFFFF) << 16 | DIAG_EMCY


Submit = Callable[[int, int], "Future[bytes | None]"]


class DiagnosisReader:
    """Reads the newest messages of 0x10F3 one SDO upload at a time: :meth:`poll` each cycle until not None.

    ``submit(index, sub_index)`` starts an upload served by the cycle. Reads sub 1
    (maximum messages) and sub 2 (newest), then up to ``last`` messages, newest
    first, walking the ring backwards; an empty sub-index ends the walk. A failed
    read raises from :meth:`poll` (an abort: the device has no history).
    """

    def __init__(self, submit: Submit, *, last: int = 8) -> None:
        self._submit = submit
        self.last = last
        self._max: int | None = None
        self._sub: int | None = None  # the next message's sub-index
        self._messages: list[DiagMessage] = []
        self._future = submit(DIAG_HISTORY, DIAG_MAX_MESSAGES)

    def poll(self) -> list[DiagMessage] | None:
        """The messages, newest first, once read; None while reads are pending."""
        while self._future.done():
            data = self._future.result() or b""
            if not data and self._sub is None:
                raise FieldbusError(f"0x{DIAG_HISTORY:04X} read returned nothing")
            if self._max is None:
                self._max = data[0]
                self._future = self._submit(DIAG_HISTORY, DIAG_NEWEST)
                continue
            if self._sub is None:
                newest = data[0]
                if newest < DIAG_FIRST_MESSAGE or not self._max:
                    return []
                self._sub = newest
            elif len(data) < DIAG_MESSAGE_HEAD:  # an empty slot: the ring has no older message
                return list(self._messages)
            else:
                self._messages.append(decode_diag_message(data))
                self._sub = (
                    self._sub - 1 if self._sub > DIAG_FIRST_MESSAGE else DIAG_FIRST_MESSAGE + self._max - 1
                )
            if len(self._messages) >= min(self.last, self._max):
                return list(self._messages)
            self._future = self._submit(DIAG_HISTORY, self._sub)
        return None


class DiagnosisHistory(DiagnosisReader):
    """:class:`DiagnosisReader` of one slave through :meth:`fieldbus.Operational.submit_sdo_read`."""

    def __init__(self, op: _SdoReader, bus: str, slave: str, *, last: int = 8) -> None:
        self.bus, self.slave = bus, slave
        super().__init__(lambda index, sub: op.submit_sdo_read(bus, slave, index, sub), last=last)


def error_code(name: str) -> int:
    """The CiA 301 / CiA 402 error code named ``name`` (as :func:`~fieldbus.core.emcy.emcy_name` names it,
    any case), e.g. ``"sensor error"`` -> 0x7300. An unknown name raises with the nearest known one."""
    wanted = name.strip().lower()
    for code, text in EXACT.items():
        if code and text.lower() == wanted:
            return code
    near = difflib.get_close_matches(wanted, [t.lower() for t in EXACT.values()], n=1, cutoff=0.6)
    hint = f"; did you mean '{near[0]}'?" if near else ""
    raise FieldbusError(f"no standard error code is named {name[:80]!r}{hint}")
