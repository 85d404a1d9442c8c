"""The CoE mailbox codec (fieldbus.core.coe_mailbox) against the emulator's SDO server.

The server (sim_slaves.ethercat.coe.SdoServer) is a separate implementation
of the slave side, also this project's: where they could share a mistake the
expected bytes are written out from ETG.1000.6 / CiA 301 instead.
"""

from __future__ import annotations

import struct

import pytest

from fieldbus.commands.demo import DEMO_MAP
from fieldbus.core.coe_mailbox import (
    MBX_TYPE_COE,
    MailboxProtocolError,
    SdoTransfer,
    decode_mailbox,
    encode_mailbox,
    next_counter,
    parse_emergency,
)
from fieldbus.core.pdo import load_drive_map
from fieldbus.errors import FieldbusError, SdoAbortError
from sim_slaves.ethercat.coe import SdoServer, emergency_payload
from sim_slaves.od import Access, CommState, ObjectDictionary

DOMAIN = 0x2100  # a writable domain entry added for the tests: any length


def _server(mailbox: int) -> SdoServer:
    od = ObjectDictionary.from_drive_map(load_drive_map(DEMO_MAP))
    od.add(DOMAIN, 0, None, b"", access=Access.RW)
    return SdoServer(od, mailbox)


def _run(t: SdoTransfer, server: SdoServer) -> tuple[bytes | None, int]:
    """Drive ``t`` against ``server`` to the end; (result, messages exchanged)."""
    for n in range(1, 1000):
        answer = server.handle(t.request(), CommState.PRE_OPERATIONAL)
        assert answer is not None
        if t.answer(answer):
            return t.result, n
    raise AssertionError("transfer never ended")


def test_expedited_upload_reads_four_bytes_in_one_message() -> None:
    t = SdoTransfer(0x1018, 1, None, mailbox_out=128)
    # CiA 301 upload initiate request: ccs 2 (0x40), index, sub-index, 4 reserved bytes; CoE service 2
    assert t.request() == struct.pack("<HBHBI", 0x2000, 0x40, 0x1018, 1, 0)
    assert _run(t, _server(128)) == ((0xFB1).to_bytes(4, "little"), 1)


def test_a_string_comes_normal_in_one_message_or_segmented_through_a_small_mailbox() -> None:
    assert _run(SdoTransfer(0x1008, 0, None, mailbox_out=128), _server(128)) == (b"demo_joint", 1)
    text = bytes(range(65, 65 + 40))
    server = _server(24)  # 24 - 6 - 10: 8 data bytes in the initiate answer, then segments of 24 - 6 - 3
    server.od.add(DOMAIN, 0, None, text, access=Access.RW)
    got, messages = _run(SdoTransfer(DOMAIN, 0, None, mailbox_out=24), server)
    assert got == text and messages == 1 + 3  # 8 bytes, then 15 + 15 + 2


def test_downloads_expedited_normal_and_segmented_land_in_the_object() -> None:
    server = _server(128)
    t = SdoTransfer(0x6060, 0, b"\x08", mailbox_out=128)
    # expedited, size indicated, n = 3 unused bytes: 0x20 | 3 << 2 | 0x02 | 0x01
    assert t.request()[2] == 0x2F
    assert _run(t, server) == (None, 1) and server.od.read(0x6060, 0) == b"\x08"
    data = bytes(range(100))
    assert _run(SdoTransfer(DOMAIN, 0, data, mailbox_out=128), server) == (None, 1)
    assert server.od.read(DOMAIN, 0) == data
    small = SdoTransfer(DOMAIN, 0, data[:30], mailbox_out=24)  # 8 in the initiate, then 15 per segment
    assert _run(small, server) == (None, 1 + 2)
    assert server.od.read(DOMAIN, 0) == data[:30]


def test_an_abort_raises_with_its_code_and_object() -> None:
    server = _server(128)
    with pytest.raises(SdoAbortError) as err:
        _run(SdoTransfer(0x1018, 1, b"\x01\x00\x00\x00", mailbox_out=128), server)  # read only
    assert (err.value.code, err.value.index, err.value.sub_index) == (0x06010002, 0x1018, 1)
    with pytest.raises(SdoAbortError) as err:
        _run(SdoTransfer(0x5FFF, 0, None, mailbox_out=128), server)
    assert err.value.code == 0x06020000  # object does not exist


def test_answers_that_do_not_fit_are_refused_or_told_apart() -> None:
    t = SdoTransfer(0x1018, 1, None, mailbox_out=128)
    other = _server(128).handle(
        SdoTransfer(0x1018, 2, None, mailbox_out=128).request(), CommState.PRE_OPERATIONAL
    )
    assert other is not None and not t.matches(other)  # an answer left over from another transfer
    mine = _server(128).handle(t.request(), CommState.PRE_OPERATIONAL)
    assert mine is not None and t.matches(mine)
    with pytest.raises(MailboxProtocolError, match="CoE service 1"):
        t.answer(emergency_payload(0x8611, 0x01))
    with pytest.raises(FieldbusError, match="out of range"):
        SdoTransfer(0x10000, 0, None, mailbox_out=128)
    with pytest.raises(FieldbusError, match="cannot carry"):
        SdoTransfer(0x1000, 0, None, mailbox_out=12)


def test_mailbox_framing_counter_and_emergency() -> None:
    buf = encode_mailbox(b"\x01\x02\x03", 5, 32)
    assert len(buf) == 32 and buf[:6] == bytes([3, 0, 0, 0, 0, 0x53])  # length 3, type CoE, counter 5
    msg = decode_mailbox(buf)
    assert (msg.type, msg.counter, msg.data) == (MBX_TYPE_COE, 5, b"\x01\x02\x03")
    with pytest.raises(MailboxProtocolError):
        decode_mailbox(struct.pack("<HHBB", 40, 0, 0, 0x13) + bytes(10))
    # 0 is only the start value: 1..7, then 1 again (ETG.1000.4)
    seq = [0]
    for _ in range(9):
        seq.append(next_counter(seq[-1]))
    assert seq == [0, 1, 2, 3, 4, 5, 6, 7, 1, 2]
    e = parse_emergency(emergency_payload(0x8611, 0x81, b"\x01\x02"))
    assert (e.error_code, e.error_register) == (0x8611, 0x81)
