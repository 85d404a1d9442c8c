"""FoE (file access over EtherCAT): the codec, the master's transfer and the emulator's server, sans IO.

The master's :class:`FoeTransfer` is played against the emulator's :class:`FoeServer`: both are
ours, so the wire format is also checked against golden bytes written from ETG.1000.6 / SOEM's
``ec_FOEt`` layout (op code, reserved, u32, data), and against pysoem and tshark in
tests/integration/test_foe_veth.py.
"""

from __future__ import annotations

import struct

import pytest

from fieldbus.core.coe_mailbox import MailboxProtocolError
from fieldbus.core.firmware_image import firmware_image, image_revision
from fieldbus.core.foe import (
    FOE_ERROR_NAMES,
    FoeError,
    FoeErrorCode,
    FoeOpCode,
    FoeTransfer,
    decode_foe,
    encode_busy,
    encode_error,
    encode_foe,
)
from fieldbus.errors import BusTimeoutError, FieldbusError
from sim_slaves.ethercat.foe import FirmwareStore, FoeServer

MBX = 128  # bytes per mailbox: a DATA carries 116


def server(size: int = MBX, **store: object) -> FoeServer:
    s = FoeServer(FirmwareStore(**store))  # type: ignore[arg-type]
    s.size_out = s.size_in = size
    return s


def play(srv: FoeServer, t: FoeTransfer, *, boot: bool = True) -> bytes | None:
    """Requests to the server and its answers back until the transfer completes; counts messages."""
    for _ in range(10_000):
        answers = srv.answers(t.request(), boot)
        assert len(answers) == 1
        if t.answer(answers[0]):
            last = t.closing()
            if last is not None:
                assert srv.answers(last, boot) == []  # a read's final ACK gets no answer
            return t.result
    raise AssertionError("no end")


def test_messages_are_op_code_reserved_u32_data() -> None:
    assert encode_foe(FoeOpCode.WRQ, 0x12345678, b"fw.efw") == b"\x02\x00\x78\x56\x34\x12fw.efw"
    assert encode_foe(FoeOpCode.DATA, 3, b"ab") == b"\x03\x00\x03\x00\x00\x00ab"
    assert encode_busy(5, 9) == b"\x06\x00\x05\x00\x09\x00"
    assert encode_error(0x8001, "x") == b"\x05\x00\x01\x80\x00\x00x"
    m = decode_foe(b"\x06\x00\x05\x00\x09\x00")
    assert (m.op, m.busy) == (FoeOpCode.BUSY, (5, 9))
    with pytest.raises(MailboxProtocolError):
        decode_foe(b"\x04\x00\x01")


def test_every_error_code_has_its_name_and_the_error_says_both() -> None:
    assert [int(c) for c in FoeErrorCode] == list(range(0x8000, 0x800C))
    assert set(FOE_ERROR_NAMES) == {int(c) for c in FoeErrorCode}
    e = FoeError(0x8008, text="firmware in BOOTSTRAP only", file="a.efw", slave="slave 2 (x)")
    assert isinstance(e, FieldbusError) and (e.code, e.name) == (0x8008, "bootstrap only")
    assert (
        str(e) == "slave 2 (x): FoE error 0x8008 bootstrap only for file 'a.efw' (firmware in BOOTSTRAP only)"
    )
    assert FoeError(0x1234).name == "unknown FoE error"


@pytest.mark.parametrize("size", [0, 1, 115, 116, 117, 3 * 116, 1000])
def test_a_file_written_then_read_back_is_the_same_at_every_packet_boundary(size: int) -> None:
    srv = server()
    data = bytes(range(256)) * 4
    data = data[:size]
    t = FoeTransfer("config.bin", data, mailbox_out=MBX, mailbox_in=MBX)
    assert play(srv, t, boot=False) is None and t.done == size
    r = FoeTransfer("config.bin", None, mailbox_out=MBX, mailbox_in=MBX)
    assert play(srv, r, boot=False) == data and r.total == size


def test_a_full_last_packet_is_followed_by_an_empty_one() -> None:
    srv = server()
    t = FoeTransfer("c.bin", bytes(116), mailbox_out=MBX, mailbox_in=MBX)
    sent = []
    while True:
        req = t.request()
        sent.append(decode_foe(req))
        if t.answer(srv.answers(req, False)[0]):
            break
    assert [(m.op, m.value, len(m.data)) for m in sent] == [(2, 0, 5), (3, 1, 116), (3, 2, 0)]


def test_busy_answers_repeat_the_same_packet_until_taken() -> None:
    srv = server(busy_answers=3)
    t = FoeTransfer("c.bin", bytes(300), mailbox_out=MBX, mailbox_in=MBX)
    requests = []
    while True:
        req = t.request()
        requests.append(req)
        if t.answer(srv.answers(req, False)[0]):
            break
    data_packets = [decode_foe(r).value for r in requests if r[0] == FoeOpCode.DATA]
    assert data_packets == [1, 1, 1, 1, 2, 3]  # packet 1 sent again after each BUSY
    assert srv.store.files["c.bin"] == bytes(300)


def test_a_slave_busy_for_ever_ends_the_transfer() -> None:
    srv = server(busy_answers=10**6)
    t = FoeTransfer("c.bin", bytes(300), mailbox_out=MBX, mailbox_in=MBX, max_busy=20)
    with pytest.raises(BusTimeoutError, match="busy for 20"):
        play(srv, t, boot=False)


def test_firmware_is_staged_and_taken_at_the_next_power_on() -> None:
    srv = server()
    image = firmware_image(0x00030002, 1000, seed=4)
    assert image_revision(image) == 0x00030002
    play(srv, FoeTransfer("app.efw", image, mailbox_out=MBX, mailbox_in=MBX))
    store = srv.store
    assert (store.active_revision, store.staged_revision, store.valid) == (None, 0x00030002, True)
    assert store.power_on() == 0x00030002 and store.staged_revision is None
    assert store.power_on() == 0x00030002  # kept over later power cycles


def refused(srv: FoeServer, t: FoeTransfer, boot: bool) -> FoeError:
    with pytest.raises(FoeError) as err:
        play(srv, t, boot=boot)
    return err.value


def test_the_server_answers_each_fault_with_its_error_code() -> None:
    srv = server(password=0x1234, capacity=500)
    image = firmware_image(7, 100)

    def foe(name: str, data: bytes | None, password: int = 0x1234) -> FoeTransfer:
        return FoeTransfer(name, data, password=password, mailbox_out=MBX, mailbox_in=MBX)

    assert refused(srv, foe("a.efw", image, password=0), True).code == FoeErrorCode.NO_RIGHTS
    assert srv.store.valid  # refused before anything was erased
    assert refused(srv, foe("missing.bin", None), False).code == FoeErrorCode.NOT_FOUND
    assert refused(srv, foe("a.efw", image), False).code == FoeErrorCode.BOOTSTRAP_ONLY
    assert refused(srv, foe("config.bin", b"x"), True).code == FoeErrorCode.NOT_BOOTSTRAP
    assert refused(srv, foe("big.bin", bytes(501)), False).code == FoeErrorCode.DISK_FULL
    damaged = bytearray(image)
    damaged[-1] ^= 0xFF
    e = refused(srv, foe("a.efw", bytes(damaged)), True)
    assert (e.code, e.text) == (FoeErrorCode.PROGRAM_ERROR, "image check failed")
    assert not srv.store.valid  # the old image was erased, the new one is no good
    # out of sequence: DATA 2 where 1 is due, and DATA with no write open
    assert decode_foe(srv.answers(encode_foe(FoeOpCode.WRQ, 0x1234, b"c.bin"), False)[0]).op == FoeOpCode.ACK
    m = decode_foe(srv.answers(encode_foe(FoeOpCode.DATA, 2, b"x"), False)[0])
    assert (m.op, m.value) == (FoeOpCode.ERR, FoeErrorCode.PACKET_NUMBER)
    m = decode_foe(srv.answers(encode_foe(FoeOpCode.DATA, 1, b"x"), False)[0])
    assert (m.op, m.value) == (FoeOpCode.ERR, FoeErrorCode.ILLEGAL)


def test_an_answer_out_of_sequence_is_a_protocol_error_and_a_stale_one_is_not_taken() -> None:
    t = FoeTransfer("c.bin", bytes(300), mailbox_out=MBX, mailbox_in=MBX)
    t.request()
    assert not t.matches(encode_foe(FoeOpCode.ACK, 7))  # an ACK of another packet: left over
    with pytest.raises(MailboxProtocolError, match="expected ACK 0"):
        t.answer(encode_foe(FoeOpCode.DATA, 1, b""))


@pytest.mark.parametrize(
    ("name", "password", "match"),
    [
        ("", 0, "1 to 255 bytes"),
        ("é€.efw", 0, "latin-1"),
        ("a.efw", -1, "password"),
        ("a" * 120, 0, "longer"),
    ],
)
def test_bad_arguments_are_named(name: str, password: int, match: str) -> None:
    with pytest.raises(FieldbusError, match=match):
        FoeTransfer(name, b"", password=password, mailbox_out=MBX, mailbox_in=MBX)


def test_a_read_longer_than_allowed_is_refused() -> None:
    srv = server()
    play(srv, FoeTransfer("c.bin", bytes(1000), mailbox_out=MBX, mailbox_in=MBX), boot=False)
    with pytest.raises(FieldbusError, match="longer than 500"):
        play(srv, FoeTransfer("c.bin", None, mailbox_out=MBX, mailbox_in=MBX, max_size=500), boot=False)


def test_golden_write_transcript() -> None:
    """The first messages of a write as SOEM's ecx_FOEwrite builds them (mailbox data only)."""
    t = FoeTransfer("fw", b"\x01\x02", password=9, mailbox_out=MBX, mailbox_in=MBX)
    assert t.request() == struct.pack("<BBI", 2, 0, 9) + b"fw"
    assert not t.answer(struct.pack("<BBI", 4, 0, 0))
    assert t.request() == struct.pack("<BBI", 3, 0, 1) + b"\x01\x02"
    assert t.answer(struct.pack("<BBI", 4, 0, 1)) and t.closing() is None
