"""Mailbox link layer of one slave (ETG.1000.4 §5.6, ETG.1000.6 §5.6).

Mailbox header (6 bytes): u16 length (of the data after the header), u16
address, u8 channel (bits 0-5) / priority (6-7), u8 type (bits 0-3: 0 error,
3 CoE, ...) / counter (bits 4-6). The master -> slave mailbox is SM0, the
slave -> master mailbox SM1.

Repeats are safe: a request whose counter (1..7) equals the previous one is
a resend and is not executed again; a lost answer is delivered again on the
master's repeat request (SM1 activate register bit 1 toggled).
"""

from __future__ import annotations

import struct
from collections import deque
from dataclasses import dataclass

from sim_slaves.ethercat.coe import SdoServer
from sim_slaves.ethercat.foe import FoeServer
from sim_slaves.od import CommState

MBX_HEADER = struct.Struct("<HHBB")
MBX_TYPE_ERROR = 0x00
MBX_TYPE_COE = 0x03
MBX_TYPE_FOE = 0x04
MBX_ERR_UNSUPPORTED_PROTOCOL = 0x0002
MBX_ERR_INVALID_HEADER = 0x0005
MBX_ERR_SIZE_TOO_SHORT = 0x0006


@dataclass(frozen=True)
class MailboxHeader:
    length: int
    address: int
    channel: int
    priority: int
    type: int
    counter: int

    @classmethod
    def decode(cls, buf: bytes) -> MailboxHeader:
        length, address, chan, tc = MBX_HEADER.unpack_from(buf, 0)
        return cls(length, address, chan & 0x3F, chan >> 6, tc & 0x0F, (tc >> 4) & 0x07)

    def encode(self) -> bytes:
        chan = self.channel & 0x3F | (self.priority & 0x03) << 6
        return MBX_HEADER.pack(self.length, self.address, chan, self.type & 0x0F | (self.counter & 0x07) << 4)


class Mailbox:
    """Queue of answers for SM1 and the request handler for SM0 (bytes in, bytes out)."""

    def __init__(self, sdo: SdoServer, size_out: int, size_in: int, foe: FoeServer | None = None) -> None:
        self.sdo = sdo
        self.foe = foe
        self.boot = False  # BOOTSTRAP: FoE only (CoE answered "unsupported protocol")
        self.size_out = size_out
        self.size_in = size_in
        self.pending: deque[bytes] = deque()
        self.last_sent = b""
        self._last_counter = 0
        self._counter = 0
        self.requests = 0
        self.duplicates = 0

    def reset(self) -> None:
        self.pending.clear()
        self.last_sent = b""
        self._last_counter = 0
        self.sdo.reset()
        if self.foe is not None:
            self.foe.reset()

    def receive(self, buf: bytes, state: CommState) -> None:
        """A complete SM0 buffer arrived from the master."""
        if len(buf) < MBX_HEADER.size:
            return
        head = MailboxHeader.decode(buf)
        if head.counter and head.counter == self._last_counter:
            self.duplicates += 1
            return
        self._last_counter = head.counter
        self.requests += 1
        if head.length > len(buf) - MBX_HEADER.size:
            self._queue(MBX_TYPE_ERROR, struct.pack("<HH", 0x0001, MBX_ERR_SIZE_TOO_SHORT))
            return
        payload = bytes(buf[MBX_HEADER.size : MBX_HEADER.size + head.length])
        if head.type == MBX_TYPE_FOE and self.foe is not None:
            self.foe.size_out, self.foe.size_in = self.size_out, self.size_in
            for answer in self.foe.answers(payload, self.boot):
                self._queue(MBX_TYPE_FOE, answer)
            return
        if head.type != MBX_TYPE_COE or self.boot:
            self._queue(MBX_TYPE_ERROR, struct.pack("<HH", 0x0001, MBX_ERR_UNSUPPORTED_PROTOCOL))
            return
        for answer in self.sdo.answers(payload, state):
            self._queue(MBX_TYPE_COE, answer)

    def send_coe(self, payload: bytes) -> None:
        """Queue an unsolicited CoE message (emergency)."""
        self._queue(MBX_TYPE_COE, payload)

    def _queue(self, kind: int, payload: bytes) -> None:
        self._counter = self._counter % 7 + 1
        head = MailboxHeader(len(payload), 0, 0, 0, kind, self._counter).encode()
        self.pending.append((head + payload)[: self.size_in].ljust(self.size_in, b"\x00"))
