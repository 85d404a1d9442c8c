"""CoE (CANopen over EtherCAT, ETG.1000.6 §5.6): SDO server and emergency messages.

Works on CoE payloads (after the 6-byte mailbox header): u16 CoE header
(number bits 0-8, service bits 12-15), then the SDO command byte, u16 index,
u8 sub-index and 4 data bytes. Expedited, normal and segmented transfers in
both directions (an empty object uploads as a normal transfer of size 0: an
expedited one carries 1-4 bytes); the SDO Information service (:mod:`sim_slaves.ethercat.sdoinfo`,
answers in fragments when they exceed the mailbox); complete access is not
offered (the SII CoE details say so). Aborts carry CiA 301 codes and travel as service 2
("SDO request"), as ETG.1000.6 prescribes and SOEM expects.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass
from enum import IntEnum

from fieldbus.errors import SdoAbortError
from sim_slaves.ethercat import sdoinfo
from sim_slaves.od import CommState, ObjectDictionary

MBX_HEADER_SIZE = 6
SDO_HEADER_SIZE = 8  # command, index, sub-index, 4 data bytes (after the CoE header)


class CoeService(IntEnum):
    EMERGENCY = 1
    SDO_REQUEST = 2
    SDO_RESPONSE = 3
    SDO_INFO = 8


ABORT_TOGGLE = 0x05030000
ABORT_COMMAND = 0x05040001
ABORT_UNSUPPORTED = 0x06010000
ABORT_GENERAL = 0x08000000

_SDO = struct.Struct("<HBHB")  # CoE header, command, index, sub-index
_SDO_FULL = struct.Struct("<HBHBI")  # ... + 4 data bytes / size


@dataclass
class _Upload:
    index: int
    sub: int
    data: bytes
    pos: int
    toggle: int


@dataclass
class _Download:
    index: int
    sub: int
    size: int
    data: bytearray
    toggle: int


class SdoServer:
    """The SDO server of one slave over its object dictionary.

    ``mailbox_in`` is the size of the slave -> master mailbox (SM1) in bytes:
    it bounds how much data one answer carries.
    """

    def __init__(self, od: ObjectDictionary, mailbox_in: int) -> None:
        self.od = od
        self.mailbox_in = mailbox_in
        self._upload: _Upload | None = None
        self._download: _Download | None = None

    def reset(self) -> None:
        self._upload = None
        self._download = None

    def answers(self, coe: bytes, state: CommState) -> list[bytes]:
        """Every CoE payload to send back for one request (SDO Information may need several)."""
        if len(coe) >= 2 and coe[1] >> 4 == CoeService.SDO_INFO:
            return sdoinfo.handle(self.od, coe, self.mailbox_in - MBX_HEADER_SIZE)
        answer = self.handle(coe, state)
        return [] if answer is None else [answer]

    def handle(self, coe: bytes, state: CommState) -> bytes | None:
        """Answer one CoE request payload; None when nothing is to be sent back."""
        if len(coe) < 2:
            return None
        service = coe[1] >> 4
        if service != CoeService.SDO_REQUEST or len(coe) < 4:
            return None
        cmd = coe[2]
        ccs = cmd >> 5
        index, sub = (coe[3] | coe[4] << 8, coe[5]) if len(coe) >= 6 else (0, 0)
        try:
            if ccs == 1:
                return self._download_initiate(coe, cmd, index, sub, state)
            if ccs == 0:
                return self._download_segment(coe, cmd, state)
            if ccs == 2:
                return self._upload_initiate(cmd, index, sub)
            if ccs == 3:
                return self._upload_segment(cmd)
            if ccs == 4:  # abort from the master
                self.reset()
                return None
            raise SdoAbortError(ABORT_COMMAND, index=index, sub_index=sub)
        except SdoAbortError as e:
            self.reset()
            return abort_payload(e.index, e.sub_index, e.code)

    # -- download (master -> slave) --

    def _download_initiate(self, coe: bytes, cmd: int, index: int, sub: int, state: CommState) -> bytes:
        self.reset()
        if cmd & 0x10:
            raise SdoAbortError(ABORT_UNSUPPORTED, index=index, sub_index=sub, detail="complete access")
        if cmd & 0x02:  # expedited
            n = 4 - ((cmd >> 2) & 0x03) if cmd & 0x01 else 4
            self.od.write(index, sub, coe[6 : 6 + n], state=state)
            return _sdo_response(0x60, index, sub)
        if not cmd & 0x01:
            raise SdoAbortError(ABORT_COMMAND, index=index, sub_index=sub, detail="size not indicated")
        (size,) = struct.unpack_from("<I", coe, 6)
        data = coe[10:]
        self.od.entry(index, sub)  # abort early for a missing object
        if len(data) >= size:
            self.od.write(index, sub, data[:size], state=state)
        else:
            self._download = _Download(index, sub, size, bytearray(data), 0)
        return _sdo_response(0x60, index, sub)

    def _download_segment(self, coe: bytes, cmd: int, state: CommState) -> bytes:
        d = self._download
        if d is None:
            raise SdoAbortError(ABORT_COMMAND, index=0, sub_index=0, detail="no download in progress")
        toggle = cmd & 0x10
        if toggle != d.toggle:
            raise SdoAbortError(ABORT_TOGGLE, index=d.index, sub_index=d.sub)
        seg = coe[3:]
        if len(coe) == 10:  # minimum-size segment: n = unused bytes of the 7
            seg = seg[: 7 - ((cmd >> 1) & 0x07)]
        d.data += seg
        d.toggle ^= 0x10
        if cmd & 0x01:
            self._download = None
            self.od.write(d.index, d.sub, bytes(d.data[: d.size]), state=state)
        return _segment_ack(0x20 | toggle)

    # -- upload (slave -> master) --

    def _upload_initiate(self, cmd: int, index: int, sub: int) -> bytes:
        self.reset()
        if cmd & 0x10:
            raise SdoAbortError(ABORT_UNSUPPORTED, index=index, sub_index=sub, detail="complete access")
        data = self.od.read(index, sub)
        if 1 <= len(data) <= 4:  # expedited carries 1-4 bytes; 0 bytes go as a normal upload of size 0
            head = 0x43 | (4 - len(data)) << 2
            return _SDO.pack(CoeService.SDO_RESPONSE << 12, head, index, sub) + data.ljust(4, b"\x00")
        room = self.mailbox_in - MBX_HEADER_SIZE - 2 - SDO_HEADER_SIZE
        first = data[:room]
        if len(first) < len(data):
            self._upload = _Upload(index, sub, data, len(first), 0)
        return _SDO_FULL.pack(CoeService.SDO_RESPONSE << 12, 0x41, index, sub, len(data)) + first

    def _upload_segment(self, cmd: int) -> bytes:
        u = self._upload
        if u is None:
            raise SdoAbortError(ABORT_COMMAND, index=0, sub_index=0, detail="no upload in progress")
        toggle = cmd & 0x10
        if toggle != u.toggle:
            raise SdoAbortError(ABORT_TOGGLE, index=u.index, sub_index=u.sub)
        room = self.mailbox_in - MBX_HEADER_SIZE - 3
        chunk = u.data[u.pos : u.pos + room]
        u.pos += len(chunk)
        u.toggle ^= 0x10
        last = u.pos >= len(u.data)
        head = toggle | (0x01 if last else 0)
        if last:
            self._upload = None
        if len(chunk) < 7:
            head |= (7 - len(chunk)) << 1
            chunk = chunk.ljust(7, b"\x00")
        return struct.pack("<HB", CoeService.SDO_RESPONSE << 12, head) + chunk


def _sdo_response(head: int, index: int, sub: int) -> bytes:
    return _SDO_FULL.pack(CoeService.SDO_RESPONSE << 12, head, index, sub, 0)


def _segment_ack(head: int) -> bytes:
    return _SDO_FULL.pack(CoeService.SDO_RESPONSE << 12, head, 0, 0, 0)


def abort_payload(index: int, sub: int, code: int) -> bytes:
    """CoE payload of an SDO abort (service 2, command 0x80, u32 abort code)."""
    return _SDO_FULL.pack(CoeService.SDO_REQUEST << 12, 0x80, index, sub, code)


def emergency_payload(error_code: int, error_register: int = 0, data: bytes = b"") -> bytes:
    """CoE payload of an emergency message (service 1): u16 code, u8 register, 5 data bytes."""
    return struct.pack("<HHB", CoeService.EMERGENCY << 12, error_code, error_register) + data[:5].ljust(
        5, b"\0"
    )
