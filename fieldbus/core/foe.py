"""File access over EtherCAT (FoE, ETG.1000.6 5.7; mailbox type 4), pure: bytes in, bytes out.

An FoE message is the mailbox data after the 6-byte mailbox header: u8
op code, u8 reserved, a u32 whose meaning depends on the op code, then
data::

    1 RRQ   read request     u32 password       file name
    2 WRQ   write request    u32 password       file name
    3 DATA  file data        u32 packet number  up to (mailbox size - 12) bytes
    4 ACK   acknowledge      u32 packet number  -
    5 ERR   error            u32 error code     error text (optional)
    6 BUSY  busy             u16 done, u16 entire  -

A write: WRQ -> ACK 0, DATA 1 -> ACK 1, ... A read: RRQ -> DATA 1,
ACK 1 -> DATA 2, ..., and the final ACK gets no answer. Either way the
file ends with the first DATA shorter than a full one (an empty DATA
after a file that fills its last packet exactly). A slave that cannot
take a DATA yet (erasing flash) answers BUSY; the master sends the same
DATA again. Error codes: :class:`FoeErrorCode` (the same codes and order
as the ESC slave stack's ``ecatfoe.h`` and Wireshark's ``packet-ecatmb.h``
op modes; SOEM's ``ethercatfoe.c`` the master's sequence; see docs/firmware.md).

:class:`FoeTransfer` is one read or write as a sequence of request
payloads and the answers they get, in the shape of
:class:`~fieldbus.core.coe_mailbox.SdoTransfer`, so that
:mod:`fieldbus.backends.ecat_mailbox` drives either one datagram at a time.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass
from enum import IntEnum

from fieldbus.core.coe_mailbox import MBX_HEADER_SIZE, MailboxProtocolError
from fieldbus.errors import BusTimeoutError, FieldbusError

MBX_TYPE_FOE = 0x04
FOE_HEADER_SIZE = 6  # op code, reserved, u32
FOE_OVERHEAD = MBX_HEADER_SIZE + FOE_HEADER_SIZE  # a mailbox of n bytes carries n - 12 bytes of file
MAX_FOE_READ = 16 << 20  # bytes accepted in one read (a longer file is refused)
MAX_BUSY = 10_000  # BUSY answers in a row before the transfer gives up
MAX_NAME = 255  # bytes of a file name

_HEAD = struct.Struct("<BBI")
_BUSY = struct.Struct("<BBHH")


class FoeOpCode(IntEnum):
    """FoE op codes (the first byte of an FoE message)."""

    RRQ = 1
    WRQ = 2
    DATA = 3
    ACK = 4
    ERR = 5
    BUSY = 6


class FoeErrorCode(IntEnum):
    """FoE error codes (ETG.1000.6; the ESC slave stack's ``ECAT_FOE_ERRCODE_*``)."""

    NOT_DEFINED = 0x8000
    NOT_FOUND = 0x8001
    ACCESS_DENIED = 0x8002
    DISK_FULL = 0x8003
    ILLEGAL = 0x8004
    PACKET_NUMBER = 0x8005
    ALREADY_EXISTS = 0x8006
    NO_USER = 0x8007
    BOOTSTRAP_ONLY = 0x8008
    NOT_BOOTSTRAP = 0x8009
    NO_RIGHTS = 0x800A
    PROGRAM_ERROR = 0x800B


FOE_ERROR_NAMES: dict[int, str] = {
    0x8000: "not defined",
    0x8001: "not found",
    0x8002: "access denied",
    0x8003: "disk full",
    0x8004: "illegal",
    0x8005: "packet number wrong",
    0x8006: "already exists",
    0x8007: "no user",
    0x8008: "bootstrap only",
    0x8009: "not bootstrap",
    0x800A: "no rights",
    0x800B: "program error",
}


def foe_error_name(code: int) -> str:
    """The name of an FoE error code, e.g. ``not found`` for 0x8001; unknown: ``unknown FoE error``."""
    return FOE_ERROR_NAMES.get(code, "unknown FoE error")


class FoeError(FieldbusError):
    """The slave answered an FoE request with an error: ``code`` (0x8000-0x800B), its ``name``, the
    slave's own ``text``, the ``file`` and ``slave`` concerned."""

    def __init__(self, code: int, *, text: str = "", file: str = "", slave: str = "") -> None:
        self.code = code
        self.name = foe_error_name(code)
        self.text = text
        self.file = file
        self.slave = slave
        where = f"{slave}: " if slave else ""
        what = f" for file '{file}'" if file else ""
        said = f" ({text})" if text else ""
        super().__init__(f"{where}FoE error 0x{code:04X} {self.name}{what}{said}")

    def __reduce__(self) -> tuple[object, ...]:
        return (_rebuild_foe_error, (self.code, self.text, self.file, self.slave))


def _rebuild_foe_error(code: int, text: str, file: str, slave: str) -> FoeError:
    return FoeError(code, text=text, file=file, slave=slave)


@dataclass(frozen=True)
class FoeMessage:
    """One FoE message: op code, its u32 (password, packet number or error code) and data."""

    op: int
    value: int
    data: bytes

    @property
    def busy(self) -> tuple[int, int]:
        """BUSY: (done, entire), the slave's progress."""
        return self.value & 0xFFFF, self.value >> 16


def encode_foe(op: int, value: int, data: bytes = b"") -> bytes:
    """An FoE message (the mailbox data): op code, reserved byte, u32 ``value``, ``data``."""
    return _HEAD.pack(op, 0, value & 0xFFFFFFFF) + data


def encode_busy(done: int, entire: int) -> bytes:
    """A BUSY message: ``done`` of ``entire`` (u16 each)."""
    return _BUSY.pack(FoeOpCode.BUSY, 0, done & 0xFFFF, entire & 0xFFFF)


def encode_error(code: int, text: str = "") -> bytes:
    """An ERR message with ``code`` and an optional text."""
    return encode_foe(FoeOpCode.ERR, code, text.encode("latin-1", "replace"))


def decode_foe(data: bytes) -> FoeMessage:
    """The FoE message in a mailbox's data; :class:`MailboxProtocolError` when shorter than its header."""
    if len(data) < FOE_HEADER_SIZE:
        raise MailboxProtocolError(f"an FoE message of {len(data)} bytes is shorter than its 6-byte header")
    op, _reserved, value = _HEAD.unpack_from(data)
    return FoeMessage(op, value, bytes(data[FOE_HEADER_SIZE:]))


def check_name(name: str) -> bytes:
    """A file name as sent (latin-1, 1..255 bytes); :class:`FieldbusError` naming it otherwise."""
    try:
        raw = name.encode("latin-1")
    except UnicodeEncodeError:
        raise FieldbusError(f"FoE file name {name!r}: only latin-1 characters can be sent") from None
    if not 0 < len(raw) <= MAX_NAME:
        raise FieldbusError(f"FoE file name {name!r}: 1 to {MAX_NAME} bytes, not {len(raw)}")
    return raw


class FoeTransfer:
    """One FoE read (``data`` None) or write, as FoE request payloads and the answers to them.

    ``mailbox_out`` / ``mailbox_in``: the slave's SM0 (master -> slave) and
    SM1 (slave -> master) sizes in bytes; a DATA carries 12 bytes less.
    Call :meth:`request` for the payload to send, :meth:`answer` with the
    FoE payload that came back; True: complete, :attr:`result` holds the
    file read (None for a write), and :meth:`closing` the last message
    that gets no answer (a read's final ACK). :attr:`done` bytes of
    :attr:`total` (a read: 0 until complete) say how far it is.
    """

    kind = MBX_TYPE_FOE

    def __init__(
        self,
        name: str,
        data: bytes | None,
        *,
        password: int = 0,
        mailbox_out: int,
        mailbox_in: int,
        max_size: int = MAX_FOE_READ,
        max_busy: int = MAX_BUSY,
    ) -> None:
        self._raw_name = check_name(name)
        if not 0 <= password <= 0xFFFFFFFF:
            raise FieldbusError(f"FoE password {password} out of range 0..0xFFFFFFFF (u32)")
        room_out, room_in = mailbox_out - FOE_OVERHEAD, mailbox_in - FOE_OVERHEAD
        if room_out < 1 or room_in < 1:
            raise FieldbusError(f"mailboxes of {mailbox_out}/{mailbox_in} bytes cannot carry FoE")
        if len(self._raw_name) > room_out:
            raise FieldbusError(f"FoE file name {name!r} longer than the mailbox carries ({room_out} bytes)")
        self.name = name
        self.data = data
        self.password = password
        self.result: bytes | None = None
        self.max_size = max_size
        self.max_busy = max_busy
        self.total = len(data) if data is not None else 0
        self.done = 0  # bytes acknowledged (write) or received (read)
        self.busy = 0  # BUSY answers to the packet in flight
        self.busy_progress: tuple[int, int] = (0, 0)  # the slave's last (done, entire)
        self._room_out, self._room_in = room_out, room_in
        self._packet = 0  # write: the packet sent last (0: the WRQ); read: the packet received last
        self._received = bytearray()
        self._closing: bytes | None = None

    @property
    def upload(self) -> bool:
        """A read (the file goes from the slave to the master)."""
        return self.data is None

    def describe(self) -> str:
        return f"FoE {'read' if self.data is None else 'write'} of '{self.name}'"

    def request(self) -> bytes:
        """The FoE payload of the next request (after a BUSY answer: the same one again)."""
        if self.data is None:
            if self._packet == 0:
                return encode_foe(FoeOpCode.RRQ, self.password, self._raw_name)
            return encode_foe(FoeOpCode.ACK, self._packet)
        if self._packet == 0:
            return encode_foe(FoeOpCode.WRQ, self.password, self._raw_name)
        return encode_foe(FoeOpCode.DATA, self._packet, self._chunk())

    def _chunk(self) -> bytes:
        assert self.data is not None
        return self.data[self.done : self.done + self._room_out]

    def closing(self) -> bytes | None:
        """The message to send after completion that gets no answer (a read's final ACK), else None."""
        return self._closing

    def matches(self, payload: bytes) -> bool:
        """Whether an FoE answer can belong to the request in flight: an ACK or DATA of an earlier packet
        (left over from a repeat or an earlier transfer) does not."""
        if len(payload) < FOE_HEADER_SIZE:
            return True
        op, _r, value = _HEAD.unpack_from(payload)
        if self.data is not None and op == FoeOpCode.ACK:
            return bool(value == self._packet)
        if self.data is None and op == FoeOpCode.DATA:
            return bool(value == self._packet + 1)
        return True

    def answer(self, payload: bytes) -> bool:
        """Take the slave's answer to the last request; True when the transfer is complete.

        Raises :class:`FoeError` for an ERR answer, :class:`MailboxProtocolError`
        for an answer that does not belong here, :class:`BusTimeoutError` after
        ``max_busy`` BUSY answers in a row.
        """
        msg = decode_foe(payload)
        if msg.op == FoeOpCode.ERR:
            text = msg.data.split(b"\0", 1)[0].decode("latin-1", "replace")
            raise FoeError(msg.value, text=text, file=self.name)
        if msg.op == FoeOpCode.BUSY:
            self.busy += 1
            self.busy_progress = msg.busy
            if self.busy > self.max_busy:
                raise BusTimeoutError(f"{self.describe()}: the slave stayed busy for {self.max_busy} answers")
            return False
        self.busy = 0
        return self._read(msg) if self.data is None else self._write(msg)

    def _unexpected(self, msg: FoeMessage, want: str) -> MailboxProtocolError:
        try:
            op = FoeOpCode(msg.op).name
        except ValueError:
            op = f"op code {msg.op}"
        return MailboxProtocolError(f"{self.describe()}: answer {op} {msg.value}, expected {want}")

    def _write(self, msg: FoeMessage) -> bool:
        if msg.op != FoeOpCode.ACK or msg.value != self._packet:
            raise self._unexpected(msg, f"ACK {self._packet}")
        if self._packet:
            sent = len(self._chunk())
            self.done += sent
            if sent < self._room_out:
                return True
        self._packet += 1
        return False

    def _read(self, msg: FoeMessage) -> bool:
        if msg.op != FoeOpCode.DATA or msg.value != self._packet + 1:
            raise self._unexpected(msg, f"DATA {self._packet + 1}")
        if len(self._received) + len(msg.data) > self.max_size:
            raise FieldbusError(f"{self.describe()}: the file is longer than {self.max_size} bytes")
        self._packet += 1
        self._received += msg.data
        self.done = len(self._received)
        if len(msg.data) < self._room_in:
            self.result = bytes(self._received)
            self.total = self.done
            self._closing = encode_foe(FoeOpCode.ACK, self._packet)
            return True
        return False
