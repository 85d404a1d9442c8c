"""CoE SDO transfers as mailbox messages (ETG.1000.4 5.6, ETG.1000.6 5.6.2), pure: bytes in, bytes out.

A mailbox message is a 6-byte header - u16 length (of the data after the
header), u16 address, u8 channel/priority, u8 type (bits 0-3: 0 error,
3 CoE) | counter (bits 4-6) - then the data, padded to the SyncManager's
length (the ESC takes a mailbox when its last byte is written). The master
writes requests into SM0 and reads answers from SM1.

A CoE payload starts with a u16 CoE header (number bits 0-8, service bits
12-15: 1 emergency, 2 SDO request, 3 SDO response), then, for an SDO, the
command byte (CiA 301 command specifier), u16 index, u8 sub-index and four
data bytes (expedited data, or the complete size). :class:`SdoTransfer`
is one upload or download as a sequence of request payloads and the
answers they get: expedited, normal (the data in the initiate message) and
segmented in both directions; an abort raises :class:`SdoAbortError`.

The counter: 0 is the start value, then 1..7 and round again without 0;
a slave takes a request with the same counter as the one before for a
repeat and does not execute it again (ETG.1000.4, mailbox header).
"""

from __future__ import annotations

import struct
from dataclasses import dataclass

from fieldbus.errors import FieldbusError, SdoAbortError

MBX_HEADER_SIZE = 6
MBX_TYPE_ERROR, MBX_TYPE_COE = 0x00, 0x03
COE_EMERGENCY, COE_SDO_REQUEST, COE_SDO_RESPONSE = 1, 2, 3
SDO_HEADER_SIZE = 8  # command, index, sub-index, 4 data bytes (after the CoE header)
SDO_MIN_SIZE = 2 + SDO_HEADER_SIZE  # CoE header + SDO header: the shortest initiate message
SEGMENT_MIN_DATA = 7  # a segment carries at least 7 data bytes (padded; CiA 301)
# command bytes (CiA 301): client (master) and server (slave) command specifiers
CMD_DOWNLOAD_INIT, CMD_UPLOAD_INIT, CMD_UPLOAD_SEGMENT, CMD_ABORT = 0x20, 0x40, 0x60, 0x80
SCS_UPLOAD_SEGMENT, SCS_DOWNLOAD_SEGMENT, SCS_UPLOAD_INIT, SCS_DOWNLOAD_INIT = 0, 1, 2, 3
EXPEDITED, SIZE_SET, LAST_SEGMENT, TOGGLE = 0x02, 0x01, 0x01, 0x10
MAX_SDO_SIZE = 0x10000  # bytes accepted in one upload (a larger announced size is refused)

_MBX = struct.Struct("<HHBB")  # length, address, channel/priority, type/counter
_SDO = struct.Struct("<HBHBI")  # CoE header, command, index, sub-index, data/size
_U16 = struct.Struct("<H")
_U32 = struct.Struct("<I")


class MailboxProtocolError(FieldbusError):
    """A mailbox answer that does not fit the request: a mailbox error reply, a wrong service, a short message."""


@dataclass(frozen=True)
class MailboxMessage:
    """One message read from a slave's SM1: its type (0 error, 3 CoE, ...), counter and data."""

    type: int
    counter: int
    data: bytes


@dataclass(frozen=True)
class Emergency:
    """A CoE emergency that came in the mailbox (CiA 301 error code and register, 5 bytes of data)."""

    error_code: int
    error_register: int
    data: bytes


def next_counter(counter: int) -> int:
    """The mailbox counter after ``counter``: 1..7, round again without 0 (0 is only the start value)."""
    return counter % 7 + 1


def encode_mailbox(data: bytes, counter: int, size: int, kind: int = MBX_TYPE_COE) -> bytes:
    """The SM0 buffer of ``size`` bytes carrying ``data`` (mailbox header, data, zero padding)."""
    if not 0 <= counter <= 7:
        raise FieldbusError(f"mailbox counter {counter} out of 0..7")
    if MBX_HEADER_SIZE + len(data) > size:
        raise FieldbusError(f"a mailbox message of {len(data)} bytes does not fit a mailbox of {size} bytes")
    return (_MBX.pack(len(data), 0, 0, kind & 0x0F | counter << 4) + data).ljust(size, b"\0")


def decode_mailbox(buf: bytes) -> MailboxMessage:
    """The message in an SM1 buffer; raises :class:`MailboxProtocolError` when its length does not fit."""
    if len(buf) < MBX_HEADER_SIZE:
        raise MailboxProtocolError(f"a mailbox of {len(buf)} bytes is shorter than its header")
    length, _address, _channel, tc = _MBX.unpack_from(buf)
    if MBX_HEADER_SIZE + length > len(buf):
        raise MailboxProtocolError(
            f"mailbox header announces {length} bytes, the mailbox holds {len(buf) - MBX_HEADER_SIZE}"
        )
    return MailboxMessage(tc & 0x0F, tc >> 4 & 0x07, bytes(buf[MBX_HEADER_SIZE : MBX_HEADER_SIZE + length]))


def mailbox_error_code(message: MailboxMessage) -> int:
    """The detail code of a mailbox error reply (type 0: u16 0x0001, u16 code; ETG.1000.4)."""
    return _U16.unpack_from(message.data, 2)[0] if len(message.data) >= 4 else 0


def coe_service(coe: bytes) -> int:
    """The CoE service of a payload (bits 12-15 of its header), 0 when too short to have one."""
    return coe[1] >> 4 if len(coe) >= 2 else 0


def parse_emergency(coe: bytes) -> Emergency:
    """A CoE emergency payload (service 1): error code, error register, data."""
    if len(coe) < 5:
        raise MailboxProtocolError(f"a CoE emergency of {len(coe)} bytes is shorter than 5")
    code, register = struct.unpack_from("<HB", coe, 2)
    return Emergency(code, register, bytes(coe[5:10]))


class SdoTransfer:
    """One SDO upload (``data`` None) or download, as CoE request payloads and the answers to them.

    ``mailbox_out``: bytes of the slave's SM0 (requests), which limits how
    much a download carries in one message; larger downloads go in
    segments. Call :meth:`request` for the payload to send, :meth:`answer`
    with the CoE payload that came back; when it returns True the transfer is
    complete and :attr:`result` holds the bytes read (None for a download).
    Validates its arguments at construction (:class:`FieldbusError`).
    """

    kind = MBX_TYPE_COE

    def __init__(self, index: int, sub_index: int, data: bytes | None, *, mailbox_out: int) -> None:
        if not 0 <= index <= 0xFFFF or not 0 <= sub_index <= 0xFF:
            raise FieldbusError(
                f"SDO object 0x{index:X}:{sub_index:X} out of range (index 16 bit, sub 8 bit)"
            )
        room = mailbox_out - MBX_HEADER_SIZE - SDO_MIN_SIZE
        if room < 0:
            raise FieldbusError(f"a mailbox of {mailbox_out} bytes cannot carry an SDO request")
        self.index = index
        self.sub_index = sub_index
        self.data = data
        self.result: bytes | None = None
        self._room = room  # data bytes a normal download carries in its initiate message
        self._segment_room = mailbox_out - MBX_HEADER_SIZE - 3  # CoE header, command byte, data
        self._toggle = 0
        self._sent = 0  # download: bytes sent so far
        self._size = 0  # upload: the complete size announced
        self._received = bytearray()
        self._initiated = False

    @property
    def upload(self) -> bool:
        return self.data is None

    def describe(self) -> str:
        return f"SDO 0x{self.index:04X}:{self.sub_index:02X}"

    def closing(self) -> bytes | None:
        """An SDO ends with an answer: no last message without one."""
        return None

    def request(self) -> bytes:
        """The CoE payload of the next request."""
        head = COE_SDO_REQUEST << 12
        if not self._initiated:
            if self.data is None:
                return _SDO.pack(head, CMD_UPLOAD_INIT, self.index, self.sub_index, 0)
            n = len(self.data)
            if n <= 4:
                cmd = CMD_DOWNLOAD_INIT | (4 - n) << 2 | EXPEDITED | SIZE_SET if n else CMD_DOWNLOAD_INIT
                return _SDO.pack(head, cmd, self.index, self.sub_index, 0)[:6] + self.data.ljust(4, b"\0")
            first = self.data[: self._room]
            return _SDO.pack(head, CMD_DOWNLOAD_INIT | SIZE_SET, self.index, self.sub_index, n) + first
        if self.data is None:
            return struct.pack("<HB", head, CMD_UPLOAD_SEGMENT | self._toggle) + bytes(SEGMENT_MIN_DATA)
        chunk = self.data[self._sent : self._sent + self._segment_room]
        last = self._sent + len(chunk) >= len(self.data)
        unused = SEGMENT_MIN_DATA - len(chunk) if len(chunk) < SEGMENT_MIN_DATA else 0
        cmd = self._toggle | unused << 1 | (LAST_SEGMENT if last else 0)
        return struct.pack("<HB", head, cmd) + chunk.ljust(SEGMENT_MIN_DATA, b"\0")

    def matches(self, coe: bytes) -> bool:
        """Whether an SDO answer can belong to this transfer's last request.

        An initiate answer or an abort names its object: one for another
        object is an answer left over from an earlier transfer. A segment
        answer names none and is taken.
        """
        if len(coe) >= SDO_MIN_SIZE and (not self._initiated or coe[2] == CMD_ABORT):
            return struct.unpack_from("<HB", coe, 3) == (self.index, self.sub_index)
        return self._initiated

    def answer(self, coe: bytes) -> bool:
        """Take the slave's answer to the last request; True when the transfer is complete.

        Raises :class:`SdoAbortError` for an abort, :class:`MailboxProtocolError`
        for an answer that does not belong to this transfer.
        """
        if len(coe) >= SDO_MIN_SIZE and coe[2] == CMD_ABORT:
            index, sub = struct.unpack_from("<HB", coe, 3)
            raise SdoAbortError(_U32.unpack_from(coe, 6)[0], index=index, sub_index=sub)
        if coe_service(coe) != COE_SDO_RESPONSE or len(coe) < 3:
            raise MailboxProtocolError(
                f"SDO 0x{self.index:04X}:{self.sub_index:02X}: answer of CoE service {coe_service(coe)} "
                f"and {len(coe)} bytes, expected an SDO response"
            )
        scs = coe[2] >> 5
        if not self._initiated:
            if len(coe) < SDO_MIN_SIZE:
                raise MailboxProtocolError(f"SDO initiate answer of {len(coe)} bytes, expected at least 10")
            index, sub = struct.unpack_from("<HB", coe, 3)
            if (index, sub) != (self.index, self.sub_index):
                raise MailboxProtocolError(
                    f"SDO answer for 0x{index:04X}:{sub:02X}, asked for 0x{self.index:04X}:{self.sub_index:02X}"
                )
            self._initiated = True
            return self._upload_initiated(coe, scs) if self.data is None else self._downloaded(coe, scs, True)
        if self.data is None:
            return self._upload_segment(coe, scs)
        return self._downloaded(coe, scs, False)

    def _expect(self, scs: int, want: int) -> None:
        if scs != want:
            raise MailboxProtocolError(
                f"SDO 0x{self.index:04X}:{self.sub_index:02X}: server command {scs}, expected {want}"
            )

    def _upload_initiated(self, coe: bytes, scs: int) -> bool:
        self._expect(scs, SCS_UPLOAD_INIT)
        cmd = coe[2]
        if cmd & EXPEDITED:
            n = 4 - (cmd >> 2 & 0x03) if cmd & SIZE_SET else 4
            self.result = bytes(coe[6 : 6 + n])
            return True
        size = _U32.unpack_from(coe, 6)[0]
        if size > MAX_SDO_SIZE:
            raise MailboxProtocolError(f"SDO upload announces {size} bytes, more than {MAX_SDO_SIZE}")
        self._size = size
        self._received += coe[SDO_MIN_SIZE : SDO_MIN_SIZE + size]
        return self._upload_done()

    def _upload_segment(self, coe: bytes, scs: int) -> bool:
        self._expect(scs, SCS_UPLOAD_SEGMENT)
        cmd = coe[2]
        if cmd & TOGGLE != self._toggle:
            raise MailboxProtocolError(
                f"SDO 0x{self.index:04X}:{self.sub_index:02X}: segment toggle bit wrong"
            )
        chunk = coe[3:]
        if len(chunk) == SEGMENT_MIN_DATA:  # a short segment, padded: n says how many bytes are unused
            chunk = chunk[: SEGMENT_MIN_DATA - (cmd >> 1 & 0x07)]
        self._received += chunk
        self._toggle ^= TOGGLE
        if cmd & LAST_SEGMENT:
            self._size = min(self._size, len(self._received))
            return self._upload_done(last=True)
        return self._upload_done()

    def _upload_done(self, *, last: bool = False) -> bool:
        if len(self._received) >= self._size or last:
            self.result = bytes(self._received[: self._size])
            return True
        return False

    def _downloaded(self, coe: bytes, scs: int, initiate: bool) -> bool:
        assert self.data is not None
        if initiate:
            self._expect(scs, SCS_DOWNLOAD_INIT)
            self._sent = len(self.data) if len(self.data) <= 4 else min(len(self.data), self._room)
        else:
            self._expect(scs, SCS_DOWNLOAD_SEGMENT)
            if coe[2] & TOGGLE != self._toggle:
                raise MailboxProtocolError(
                    f"SDO 0x{self.index:04X}:{self.sub_index:02X}: segment toggle bit wrong"
                )
            self._sent += min(len(self.data) - self._sent, self._segment_room)
            self._toggle ^= TOGGLE
        return self._sent >= len(self.data)
