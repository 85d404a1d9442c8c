"""A slave's CoE mailbox driven one datagram at a time, for SDO transfers inside the cycle.

SOEM's SDO calls block: ``ecx_mbxsend`` waits up to ``EC_TIMEOUTTXM`` (20 ms)
for SM0 to be free, ``ecx_mbxreceive`` polls SM1 until its timeout. Here a
transfer is a generator; each step sends exactly one datagram through a
:class:`RegisterPort` and then yields, so the cycle that advances it waits
for one reply at most (the port's timeout):

1. write the request into SM0 (FPWR of the whole SyncManager, so the ESC takes
   it); a refused write (SM0 still full, or the reply lost) is sent again next
   step with the same counter - a slave that took it already sees a repeat;
2. poll SM1's status register (0x080D, bit 3 "mailbox full") with FPRD - the
   same datagram reads SM1's activate and PDI control bytes (0x080E-0x080F);
3. read SM1 (FPRD of the whole SyncManager, which frees it); an emergency is
   handed to ``on_emergency`` and the poll goes on; an SDO answer for another
   object (left over from a transfer that timed out) is dropped;
4. the answer goes to the :class:`~fieldbus.core.coe_mailbox.SdoTransfer`:
   complete, or the next segment from step 1.

A read whose reply is lost: if SM1 still shows full, the frame never reached
the slave and the read is made again; if SM1 is empty, the ESC released the
answer and it is asked for again with the mailbox repeat request (ETG.1000.4:
toggle bit 1 of SM1's activate register, FPWR 0x080E), then polled as before.
A deadline in steps ends the transfer with :class:`BusTimeoutError`: the
cycle gives a transfer at most one step per cycle and none while the bus
recovers, so steps, not wall time, say how long the slave had to answer.

The same steps carry an FoE transfer (:class:`~fieldbus.core.foe.FoeTransfer`,
mailbox type 4: firmware and files): any :class:`MailboxTransfer` - its
mailbox type, requests and answers - goes through them. An FoE read ends
with an ACK that gets no answer: written (step 1) after the last answer.
"""

from __future__ import annotations

import struct
from collections.abc import Callable, Generator
from dataclasses import dataclass
from typing import Protocol

from fieldbus.core.coe_mailbox import (
    COE_EMERGENCY,
    COE_SDO_REQUEST,
    COE_SDO_RESPONSE,
    MBX_TYPE_COE,
    MBX_TYPE_ERROR,
    MailboxProtocolError,
    coe_service,
    decode_mailbox,
    encode_mailbox,
    mailbox_error_code,
    next_counter,
    parse_emergency,
)
from fieldbus.errors import BusTimeoutError

REG_SM0, REG_SM1_STATUS, REG_SM1_ACTIVATE = 0x0800, 0x080D, 0x080E  # SM0; SM1 status, activate bytes
SM_MAILBOX_FULL = 0x08  # SM status bit 3: the mailbox buffer is written and not yet read
SM_REPEAT = 0x02  # SM activate bit 1: repeat request (toggled by the master)


class MailboxTransfer(Protocol):
    """One transfer through a mailbox (an SDO, an FoE read or write): requests out, answers in."""

    kind: int  # mailbox type of its messages (3 CoE, 4 FoE)
    result: bytes | None

    def describe(self) -> str: ...

    def request(self) -> bytes:
        """The payload of the next request."""

    def matches(self, payload: bytes) -> bool:
        """False for an answer left over from an earlier request or transfer (dropped)."""

    def answer(self, payload: bytes) -> bool:
        """Take an answer; True when the transfer is complete."""

    def closing(self) -> bytes | None:
        """A last message after completion that gets no answer, or None."""


class RegisterPort(Protocol):
    """One slave's registers, one datagram per call, each waiting a bounded time for its reply."""

    def read(self, ado: int, size: int) -> bytes | None:
        """FPRD of ``size`` bytes at ``ado``; None when no reply came in time or the WKC was not 1."""

    def write(self, ado: int, data: bytes) -> bool:
        """FPWR of ``data`` at ``ado``; False when no reply came in time or the WKC was not 1."""


@dataclass(frozen=True)
class MailboxLayout:
    """Where a slave's mailboxes are: SM0 (master -> slave) and SM1 (slave -> master), bytes."""

    out_start: int
    out_size: int
    in_start: int
    in_size: int

    @classmethod
    def from_sm_registers(cls, raw: bytes) -> MailboxLayout | None:
        """From the 16 bytes of registers 0x0800-0x080F (SM0, SM1); None when the slave has no mailbox."""
        o_start, o_size = struct.unpack_from("<HH", raw, 0)
        i_start, i_size = struct.unpack_from("<HH", raw, 8)
        if not o_size or not i_size:
            return None
        return cls(o_start, o_size, i_start, i_size)


class SlaveMailbox:
    """One slave's mailbox as the master drives it: its layout, port and the counter of its requests.

    ``counter``: the last counter used. None at first: SOEM, which served
    the slave during bring-up, counts 1..7 and does not say where it
    stopped, so the first request here carries 0 (the start value, which SOEM
    never sends) and cannot be taken for a repeat of SOEM's last; the backend
    makes that first request a harmless read at bring-up.
    """

    def __init__(
        self,
        layout: MailboxLayout,
        port: RegisterPort,
        on_emergency: Callable[[int, int], None] | None = None,
    ) -> None:
        self.layout = layout
        self.port = port
        self.on_emergency = on_emergency
        self.counter: int | None = None
        self.stale_answers = 0  # answers dropped because they belonged to an earlier transfer
        self.repeats = 0  # repeat requests sent (an answer whose read reply was lost)

    def take_counter(self) -> int:
        self.counter = 0 if self.counter is None else next_counter(self.counter)
        return self.counter

    def transfer(
        self, t: MailboxTransfer, max_steps: int, *, per_answer: bool = False
    ) -> Generator[None, None, bytes | None]:
        """Run ``t`` to the end, one datagram per step; returns the bytes read (None for a download).

        At most ``max_steps`` steps (datagrams) - for the whole transfer, or,
        ``per_answer``, from one answer to the next (a long file) - the one
        after that raises :class:`BusTimeoutError` instead. The last step (the
        read of the final answer, or the write of a closing message) returns
        without a further yield: the caller's step ends there.
        """
        lay, port = self.layout, self.port
        steps = 1

        def waited() -> None:
            nonlocal steps
            steps += 1
            if steps > max_steps:
                raise BusTimeoutError(f"no complete answer to {t.describe()} in {max_steps} datagrams")

        while True:
            message = encode_mailbox(t.request(), self.take_counter(), lay.out_size, t.kind)
            while not port.write(lay.out_start, message):
                yield
                waited()
            lost = False  # a read of SM1 got no reply
            repeat: int | None = None  # SM1 activate byte with the repeat request asked for
            while True:
                yield
                waited()
                status = port.read(REG_SM1_STATUS, 3)
                if status is None:
                    continue
                if not status[0] & SM_MAILBOX_FULL:
                    if lost:  # the ESC released the answer whose reply was lost: ask for it again
                        repeat = status[1] ^ SM_REPEAT if repeat is None else repeat
                        if status[1] != repeat:
                            yield
                            waited()
                            port.write(REG_SM1_ACTIVATE, bytes([repeat]))
                            self.repeats += 1
                    continue
                repeat = None  # full: a repeat asked for is served; a later loss asks again
                yield
                waited()
                buf = port.read(lay.in_start, lay.in_size)
                if buf is None:
                    lost = True
                    continue
                lost, repeat = False, None
                coe = self._answer(t, buf)
                if coe is not None:
                    break
            if t.answer(coe):
                last = t.closing()
                if last is not None:
                    yield
                    waited()
                    closing = encode_mailbox(last, self.take_counter(), lay.out_size, t.kind)
                    while not port.write(lay.out_start, closing):
                        yield
                        waited()
                return t.result
            if per_answer:
                steps = 0
            yield
            waited()

    def _answer(self, t: MailboxTransfer, buf: bytes) -> bytes | None:
        """The payload in ``buf`` when it answers ``t``; None for what is not (emergency, stale)."""
        msg = decode_mailbox(buf)
        if msg.type == MBX_TYPE_ERROR:
            raise MailboxProtocolError(f"{t.describe()}: mailbox error 0x{mailbox_error_code(msg):04X}")
        if msg.type == MBX_TYPE_COE and coe_service(msg.data) == COE_EMERGENCY:
            e = parse_emergency(msg.data)
            if self.on_emergency is not None:
                self.on_emergency(e.error_code, e.error_register)
            return None
        if msg.type != t.kind:
            return None  # another protocol (EoE, ...): not ours
        stale = not t.matches(msg.data)
        if t.kind == MBX_TYPE_COE and coe_service(msg.data) not in (COE_SDO_RESPONSE, COE_SDO_REQUEST):
            stale = False  # another CoE service: the transfer's answer() names it
        if stale:
            self.stale_answers += 1
            return None
        return msg.data
